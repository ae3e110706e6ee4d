"""Window mode: find each recipe mark near where the prior pose predicts it, keeping its identity.

A mark's window is its predicted ellipse widened by how far the mark can move when the part is
anywhere within the recipe's tolerances (``max_offset_mm``, ``max_offset_deg``), computed from the
geometry of this camera. Accepted candidates from all windows are assigned to marks jointly (least
total distance to the predictions), so two marks never take the same blob.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from mvpose_core.detect.geometry import MarkPrediction, predict_marks
from mvpose_core.detect.refine import Candidate, Measurement, find_candidates, measure
from mvpose_core.detect.types import DetectOptions, MarkDetection, check_image
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array


def detect_marks(
    image: np.ndarray,
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf_prior: Array,
    options: DetectOptions = DetectOptions(),
) -> list[MarkDetection]:
    """One detection per mark the recipe expects ``cam`` to see, found or with the reason why not."""
    image = check_image(image, cam.model, f"camera {cam.key!r}")
    preds = predict_marks(
        cam, recipe, T_rf_from_pf_prior, options.size_tolerance, options.shape_slack_deg
    )
    dark = recipe.polarity == "dark_on_light"
    H, W = image.shape
    results: dict[str, MarkDetection] = {}
    accepted: list[tuple[Measurement, MarkDetection]] = []  # shared pool for the assignment
    live: list[MarkPrediction] = []
    for p in preds:
        mid = p.mark.mark_id
        if not p.facing:
            results[mid] = MarkDetection.missing(mid, "mark faces away from the camera")
            continue
        half = p.max_shift_px + p.radius_range[1] + options.window_extra_px
        u0, v0 = int(np.floor(p.uv[0] - half)), int(np.floor(p.uv[1] - half))
        u1, v1 = int(np.ceil(p.uv[0] + half)) + 1, int(np.ceil(p.uv[1] + half)) + 1
        box = (max(u0, 0), max(v0, 0), min(u1, W), min(v1, H))
        if box[2] - box[0] < 8 or box[3] - box[1] < 8:
            results[mid] = MarkDetection.missing(mid, "outside image")
            continue
        live.append(p)
        scale = coarse_scale(p.radius_range[0])
        cands = find_candidates(
            image, box, dark, p.radius_range, options.min_contrast, scale, options.max_candidates
        )
        # If nothing is accepted, the mark is reported with what was wrong with the nearest blob.
        reason, nearest = "nothing mark-like in window", np.inf
        for c in cands:
            if any(np.hypot(*(c.ellipse.centre - d.uv_ellipse)) < 2.0 for _, d in accepted):
                continue  # the same blob seen through an overlapping window
            det, why = _measure_candidate(image, c, p, dark, options, scale)
            if det is not None:
                accepted.append(det)
            elif (dist := float(np.hypot(*(c.ellipse.centre - p.uv)))) < nearest:
                reason, nearest = f"{why} (blob at {dist:.0f} px from prediction)", dist
        results[mid] = MarkDetection.missing(mid, reason)
    _assign(live, accepted, results, options)
    return [results[p.mark.mark_id] for p in preds]


def coarse_scale(min_radius_px: float) -> int:
    """Largest reduction (1, 2, 4, 8) at which the smallest accepted mark keeps a 2.5 px radius."""
    scale = 1
    while scale < 8 and min_radius_px / (2 * scale) >= 2.5:
        scale *= 2
    return scale


def _measure_candidate(
    image: np.ndarray,
    cand: Candidate,
    pred: MarkPrediction,
    dark: bool,
    options: DetectOptions,
    scale: int,
) -> tuple[tuple[Measurement, MarkDetection] | None, str | None]:
    """Measure a candidate and check it against the prediction; (measurement, detection) or reason."""
    m = measure(
        image,
        cand.ellipse,
        dark,
        options.min_contrast,
        options.max_fit_residual_px,
        options.min_edge_fraction,
        search_px=2.0 + 1.5 * scale + 0.15 * cand.ellipse.radius,
    )
    if m.ellipse is None:
        return None, m.reason
    e = m.ellipse
    lo, hi = pred.radius_range
    if not lo <= e.radius <= hi:
        return None, f"size {e.radius:.1f} px outside [{lo:.1f}, {hi:.1f}]"
    rlo, rhi = pred.ratio_range
    if not rlo <= e.axis_ratio <= rhi:
        return None, f"shape: axis ratio {e.axis_ratio:.2f} outside [{rlo:.2f}, {rhi:.2f}]"
    det = MarkDetection(
        mark_id="",
        found=True,
        uv=e.centre.copy(),
        contrast=m.contrast,
        fit_residual_px=m.fit_residual_px,
        axis_ratio=e.axis_ratio,
        radius_px=e.radius,
        uv_ellipse=e.centre.copy(),
        correction=np.zeros(2),
        edge_points=m.edge_points,
    )
    return (m, det), None


def _assign(
    preds: list[MarkPrediction],
    pool: list[tuple[Measurement, MarkDetection]],
    results: dict[str, MarkDetection],
    options: DetectOptions,
) -> None:
    """Give each predicted mark at most one accepted blob, minimising the total distance."""
    if not preds or not pool:
        return
    uv = np.array([d.uv_ellipse for _, d in pool])
    pred_uv = np.array([p.uv for p in preds])
    dist = np.linalg.norm(pred_uv[:, None, :] - uv[None, :, :], axis=2)
    gate = np.array([p.max_shift_px + options.window_extra_px for p in preds])
    cost = np.where(dist <= gate[:, None], dist, 1e9)
    rows, cols = linear_sum_assignment(cost)
    for r, c in zip(rows, cols, strict=True):
        if cost[r, c] >= 1e9:
            continue
        p = preds[r]
        det = pool[c][1]
        corr = p.correction if options.correct_perspective else np.zeros(2)
        results[p.mark.mark_id] = MarkDetection(
            mark_id=p.mark.mark_id,
            found=True,
            uv=det.uv_ellipse + corr,  # type: ignore[operator]
            contrast=det.contrast,
            fit_residual_px=det.fit_residual_px,
            axis_ratio=det.axis_ratio,
            radius_px=det.radius_px,
            uv_ellipse=det.uv_ellipse,
            correction=corr.copy(),
            edge_points=det.edge_points,
        )

