"""A reproduction of the paper's mark extraction (Section 2.3), as the baseline for bench_detect.

Global automatic (Otsu) threshold of the whole frame, connected components with their areas and
bounding boxes, candidates kept by area and shape, and each centre from a Hough circle transform
on the candidate's neighbourhood. Marks are named by the nearest predicted position, as a window
scheme would. Not used by mvpose itself; it exists to compare speed and accuracy.
"""

from __future__ import annotations

import cv2
import numpy as np

from mvpose_core.detect.geometry import MarkPrediction


def paper_detect(
    image: np.ndarray, preds: list[MarkPrediction], dark: bool
) -> dict[str, np.ndarray]:
    """Centres (px) of the predicted marks found by the paper's recipe, keyed by mark id."""
    mode = (cv2.THRESH_BINARY_INV if dark else cv2.THRESH_BINARY) | cv2.THRESH_OTSU
    _, binary = cv2.threshold(image, 0, 255, mode)
    n, _, stats, centroids = cv2.connectedComponentsWithStats(binary, connectivity=8)
    r_lo = min(p.radius_range[0] for p in preds)
    r_hi = max(p.radius_range[1] for p in preds)
    out: dict[str, np.ndarray] = {}
    cands = []
    for k in range(1, n):
        x, y, w, h, area = stats[k]
        if not np.pi * r_lo**2 <= area <= np.pi * r_hi**2:
            continue
        if min(w, h) / max(w, h) < 0.6 or area / (w * h) < 0.6:  # roughly round and filled
            continue
        pad = int(r_hi) + 4
        x0, y0 = max(x - pad // 2, 0), max(y - pad // 2, 0)
        roi = image[y0 : y + h + pad // 2, x0 : x + w + pad // 2]
        circles = cv2.HoughCircles(
            roi,
            cv2.HOUGH_GRADIENT,
            dp=1,
            minDist=2 * r_hi,
            param1=100,
            param2=10,
            minRadius=int(r_lo),
            maxRadius=int(np.ceil(r_hi)),
        )
        if circles is None:
            continue
        cx, cy, _ = circles[0, 0]
        cands.append(np.array([cx + x0, cy + y0], dtype=float))
    for p in preds:
        if not cands:
            break
        d = [np.linalg.norm(c - p.uv) for c in cands]
        k = int(np.argmin(d))
        if d[k] <= p.max_shift_px:
            out[p.mark.mark_id] = cands[k]
    return out
