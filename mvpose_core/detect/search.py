"""Search mode: find every mark-like blob in a whole frame with no prior pose (teaching, recovery).

Coarse to fine: candidates on a reduced frame (a top-hat, Otsu, contours: a few milliseconds,
never connected components on the full frame), then each one measured on full-resolution pixels
like in window mode. The expected size comes from the recipe at its reference pose, widened by
the recipe's tolerances. :func:`identify_marks` then names the blobs from a pose guess.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.optimize import linear_sum_assignment

from mvpose_core.detect.candidates import find_candidates
from mvpose_core.detect.geometry import MarkPrediction, predict_marks
from mvpose_core.detect.refine import measure_many
from mvpose_core.detect.types import DetectOptions, MarkDetection, check_image
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array


def search_marks(
    image: np.ndarray,
    cam: ViewCamera,
    recipe: RecipeConfig,
    options: DetectOptions = DetectOptions(),  # noqa: B008 - frozen, immutable default
) -> list[MarkDetection]:
    """Every accepted mark-like blob in the frame, named ``"?0"``, ``"?1"``… in reading order.

    Centres are ellipse centres (no perspective correction: the pose is unknown); use
    :func:`identify_marks` to name them and correct them.
    """
    image = check_image(image, cam.model, f"camera {cam.key!r}")
    preds = [
        p
        for p in predict_marks(
            cam,
            recipe,
            recipe.T_rf_from_pf0.matrix,
            options.size_tolerance,
            options.shape_slack_deg,
            mark_ids=[m.id for m in recipe.marks],
        )
        if p.facing
    ]
    if not preds:
        raise ValueError(f"camera {cam.key!r}: no mark of recipe {recipe.name!r} faces this camera")
    found: list[MarkDetection] = []
    for dark in sorted({p.dark for p in preds}, reverse=True):
        # Marks of one polarity at a time: light and dark marks are different blobs.
        same = [p for p in preds if p.dark == dark]
        found += _search_polarity(image, same, dark, options)
    found.sort(key=lambda d: (round(float(d.uv[1]) / 8.0), float(d.uv[0])))  # type: ignore[index]
    return [replace(d, mark_id=f"?{k}") for k, d in enumerate(found)]


def _search_polarity(
    image: np.ndarray, preds: list[MarkPrediction], dark: bool, options: DetectOptions
) -> list[MarkDetection]:
    """The accepted blobs of one polarity, sized like any of ``preds``."""
    r_lo = min(p.radius_range[0] for p in preds)
    r_hi = max(p.radius_range[1] for p in preds)
    ratio_lo = min(p.ratio_range[0] for p in preds)
    H, W = image.shape
    scale = options.search_scale
    while scale > 1 and r_lo / scale < 2.5:
        scale //= 2
    cands = find_candidates(
        image, (0, 0, W, H), dark, (r_lo, r_hi), options.min_contrast, scale, options.max_candidates
    )
    measured = measure_many(
        image,
        [c.ellipse for c in cands],
        dark,
        options.min_contrast,
        options.max_fit_residual_px,
        options.min_edge_fraction,
        search_px=2.0 + scale + 0.1 * r_hi,
    )
    found: list[MarkDetection] = []
    for m in measured:
        e = m.ellipse
        if e is None or not (r_lo <= e.radius <= r_hi) or e.axis_ratio < ratio_lo:
            continue
        found.append(
            MarkDetection.unnamed(
                e.centre, e.radius, e.axis_ratio, m.contrast, m.fit_residual_px, m.edge_points
            )
        )
    return found


def identify_marks(
    blobs: list[MarkDetection],
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf: Array,
    max_distance_px: float,
    options: DetectOptions = DetectOptions(),  # noqa: B008 - frozen, immutable default
) -> list[MarkDetection]:
    """Name search-mode blobs after the sighted marks they are nearest to at ``T_rf_from_pf``.

    One-to-one (least total distance); a mark with no blob within ``max_distance_px`` is reported
    missing. Named marks get the perspective correction at ``T_rf_from_pf``.
    """
    preds = predict_marks(
        cam, recipe, T_rf_from_pf, options.size_tolerance, options.shape_slack_deg
    )
    out = {
        p.mark.mark_id: MarkDetection.missing(p.mark.mark_id, "no blob near prediction")
        for p in preds
    }
    live = [b for b in blobs if b.found and b.uv_ellipse is not None]
    if preds and live:
        pred_uv = np.array([p.uv for p in preds])
        uv = np.array([b.uv_ellipse for b in live])
        dist = np.linalg.norm(pred_uv[:, None, :] - uv[None, :, :], axis=2)
        cost = np.where(dist <= max_distance_px, dist, 1e9)
        for r, c in zip(*linear_sum_assignment(cost), strict=True):
            if cost[r, c] >= 1e9 or not preds[r].facing:
                continue
            p, b = preds[r], live[c]
            corr = p.correction if options.correct_perspective else np.zeros(2)
            out[p.mark.mark_id] = replace(
                b,
                mark_id=p.mark.mark_id,
                uv=b.uv_ellipse + corr,
                correction=corr.copy(),
            )
    return [out[p.mark.mark_id] for p in preds]
