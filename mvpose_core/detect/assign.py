"""An image's blobs measured, judged against their marks, and given to them.

The windows' search (window.py) leaves, per image, its predictions and the blobs found in each
mark's window (:class:`Search`). All images' blobs are measured in one batch
(:func:`measure_all`); a measured blob that looks like its mark (size and shape within the
mark's ranges, :func:`check`) is accepted, and the accepted blobs are given to the marks jointly,
at most one each, by least total distance to the predictions within each mark's gate
(:func:`assign`), with the perspective correction its prediction carries.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from mvpose_core.detect.candidates import Candidate
from mvpose_core.detect.geometry import MarkPrediction
from mvpose_core.detect.refine import Measurement, measure_in
from mvpose_core.detect.types import DetectOptions, MarkDetection
from mvpose_core.station import RecipeConfig


@dataclass
class Search:
    """One image's windows and the candidate blobs found in them, before measurement."""

    preds: list[MarkPrediction]
    results: dict[str, MarkDetection]  # per mark: missing (with the reason) until accepted
    live: list[MarkPrediction]  # the predictions whose window lies in the image
    cands: list[tuple[int, Candidate]]  # (index in live, blob): one entry per distinct blob
    scales: list[int]  # per blob: the reduction its window was searched at


def measure_all(
    searches: list[Search], images: list[np.ndarray], recipe: RecipeConfig,
    options: DetectOptions,
) -> list[list[MarkDetection]]:
    """Measure the candidates of every search in one batch and conclude each image."""
    owner = np.array([k for k, s in enumerate(searches) for _ in s.cands], dtype=np.intp)
    measured: list[Measurement] = []
    if len(owner):
        # An image's blobs have their rims looked for within the image's finest coarse pixel
        # and a tenth of its largest blob's radius.
        reach_px = [
            2.0 + min(s.scales) + 0.1 * max(c.ellipse.radius for _, c in s.cands)
            if s.cands else 0.0
            for s in searches
        ]
        measured = measure_in(
            images,
            owner,
            [c.ellipse for s in searches for _, c in s.cands],
            np.array([s.live[k].dark for s in searches for k, _ in s.cands], dtype=bool),
            options.min_contrast,
            options.max_fit_residual_px,
            options.min_edge_fraction,
            search_px=np.array([reach_px[k] for k in owner.tolist()]),
        )
    out = []
    first = 0
    for s in searches:
        n = len(s.cands)
        out.append(conclude(s, measured[first : first + n], options))
        first += n
    return out


def conclude(
    s: Search, measured: list[Measurement], options: DetectOptions
) -> list[MarkDetection]:
    """Accept the measured blobs that look like their marks and give each mark at most one."""
    results = s.results
    accepted: list[MarkDetection] = []
    nearest = np.full(len(s.live), np.inf)  # a missing mark reports its nearest blob's fault
    for (k, c), m in zip(s.cands, measured, strict=True):
        p = s.live[k]
        det, why = check(m, p)
        if det is not None:
            accepted.append(det)
        elif (dist := float(np.hypot(*(c.ellipse.centre - p.uv)))) < nearest[k]:
            nearest[k] = dist
            results[p.mark.mark_id] = MarkDetection.missing(
                p.mark.mark_id,
                f"{why} (blob at {dist:.0f} px from prediction)",
                contrast=m.contrast,
                fit_residual_px=m.fit_residual_px,
            )
    assign(s.live, accepted, results, options)
    return [results[p.mark.mark_id] for p in s.preds]


def check(m: Measurement, pred: MarkPrediction) -> tuple[MarkDetection | None, str | None]:
    """An unnamed detection if the measured blob looks like the predicted mark, else the reason."""
    if m.ellipse is None:
        return None, m.reason
    e = m.ellipse
    lo, hi = pred.radius_range
    if not lo <= e.radius <= hi:
        return None, f"size {e.radius:.1f} px outside [{lo:.1f}, {hi:.1f}]"
    rlo, rhi = pred.ratio_range
    if not rlo <= e.axis_ratio <= rhi:
        return None, f"shape: axis ratio {e.axis_ratio:.2f} outside [{rlo:.2f}, {rhi:.2f}]"
    det = MarkDetection.unnamed(
        e.centre, e.radius, e.axis_ratio, m.contrast, m.fit_residual_px, m.edge_points
    )
    return det, None


def assign(
    preds: list[MarkPrediction],
    pool: list[MarkDetection],
    results: dict[str, MarkDetection],
    options: DetectOptions,
) -> None:
    """Give each predicted mark at most one accepted blob, minimising the total distance."""
    if not preds or not pool:
        return
    uv = np.array([d.uv_ellipse for d in pool])
    pred_uv = np.array([p.uv for p in preds])
    dist = np.linalg.norm(pred_uv[:, None, :] - uv[None, :, :], axis=2)
    gate = np.array([gate_px(p, options) for p in preds])
    cost = np.where(dist <= gate[:, None], dist, 1e9)
    rows, cols = linear_sum_assignment(cost)
    taken = {int(c) for r, c in zip(rows, cols, strict=True) if cost[r, c] < 1e9}
    for r, c in zip(rows, cols, strict=True):
        if cost[r, c] >= 1e9:
            continue
        p = preds[r]
        det = pool[c]
        corr = p.correction if options.correct_perspective else np.zeros(2)
        # The mark's next candidates: accepted blobs within its gate that no mark took, nearest
        # first; the estimator tries them when this one disagrees with the rest (engine.md).
        others = [j for j in np.argsort(dist[r]).tolist()
                  if j not in taken and cost[r, j] < 1e9][: options.max_alternates]
        results[p.mark.mark_id] = MarkDetection(
            mark_id=p.mark.mark_id, found=True, uv=det.uv_ellipse + corr, contrast=det.contrast,
            fit_residual_px=det.fit_residual_px, axis_ratio=det.axis_ratio,
            radius_px=det.radius_px, uv_ellipse=det.uv_ellipse, correction=corr.copy(),
            edge_points=det.edge_points,
            alternates=tuple((float(uv[j, 0]), float(uv[j, 1])) for j in others),
        )


def gate_px(p: MarkPrediction, options: DetectOptions) -> float:
    """How far from its prediction (px) a mark may be given a blob (:func:`assign`)."""
    return p.max_shift_px + options.window_extra_px
