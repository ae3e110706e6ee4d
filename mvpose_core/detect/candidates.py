"""Find mark candidates in an image region: blobs of a mark's polarity and rough size.

A morphological top-hat (flattens illumination and panel edges) thresholded by Otsu, one pixel
peeled off, external contours, area and rough-shape filters, an ellipse per contour; on the
region reduced so that the smallest accepted mark keeps a radius of 2.5 px. The candidates are
then measured on full-resolution pixels (refine.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from mvpose_core.detect.ellipse import Ellipse

_CROSS = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))


@dataclass(frozen=True)
class Candidate:
    """A blob that may be a mark: a rough ellipse from its contour (full-resolution pixels)."""

    ellipse: Ellipse
    area_px: float


def find_candidates(
    image: np.ndarray,
    box: tuple[int, int, int, int],
    dark: bool,
    radius_range: tuple[float, float],
    min_contrast: float,
    scale: int,
    max_candidates: int,
) -> list[Candidate]:
    """Blobs of the right polarity and roughly the right size inside ``box`` = (u0, v0, u1, v1)."""
    u0, v0, u1, v1 = box
    roi = image[v0:v1, u0:u1]
    if scale > 1:
        w, h = (u1 - u0) // scale, (v1 - v0) // scale
        if w < 8 or h < 8:
            return []
        # Every scale-th pixel, no averaging: only candidates are looked for here (the blobs
        # keep a radius of at least 2.5 coarse px) and the measurement uses full-resolution
        # pixels; area or linear resampling of these large windows costs 4-10x more.
        first = scale // 2
        roi = np.ascontiguousarray(roi[first : h * scale : scale, first : w * scale : scale])
    r_lo, r_hi = radius_range[0] / scale, radius_range[1] / scale
    # Black (white) top-hat: closing with a square too big to fit inside a mark erases the marks
    # and keeps what is larger (panel edges, illumination, big holes); the difference is the marks.
    side = int(np.ceil(2.0 * r_hi)) + 3
    if side >= min(roi.shape):
        return []
    kernel = _square(side)
    hat = cv2.morphologyEx(roi, cv2.MORPH_BLACKHAT if dark else cv2.MORPH_TOPHAT, kernel)
    otsu, binary = cv2.threshold(hat, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    level = max(0.5 * min_contrast, otsu)
    if cv2.minMaxLoc(hat)[1] <= level:
        return []
    if level != otsu:
        _, binary = cv2.threshold(hat, level, 255, cv2.THRESH_BINARY)
    # Peel one pixel so that a mark touching clutter (a hole a few px away merges at reduced
    # scale) still comes out as its own blob; the pixel is given back to the ellipse below.
    binary = cv2.erode(binary, _CROSS)
    contours, _ = cv2.findContours(binary, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    # Coarse pixels and blur blunt the contour: be lenient on area here, strict after measuring.
    a_lo = np.pi * (0.5 * r_lo) ** 2
    a_hi = np.pi * (1.3 * r_hi + 1.0) ** 2
    out: list[Candidate] = []
    for c in contours:
        if len(c) < 5:
            continue
        area = cv2.contourArea(c)
        if not a_lo <= area <= a_hi:
            continue
        (cx, cy), (d1, d2), ang = cv2.fitEllipse(c)
        if min(d1, d2) <= 0 or min(d1, d2) / max(d1, d2) < 0.2:
            continue
        a, b, angle = 0.5 * d1, 0.5 * d2, np.deg2rad(ang)
        if b > a:
            a, b, angle = b, a, angle + 0.5 * np.pi
        # The blob must fill its ellipse: rejects rings, crescents, and branched shapes.
        if area < 0.7 * np.pi * a * b:
            continue
        a, b = a + 1.0, b + 1.0  # the peeled pixel
        centre = np.array([cx * scale + scale // 2 + u0, cy * scale + scale // 2 + v0])
        out.append(
            Candidate(Ellipse(centre, a * scale, b * scale, float(angle)), area * scale * scale)
        )
        if len(out) >= max_candidates:
            break
    return out


@lru_cache(maxsize=64)
def _square(side: int) -> np.ndarray:
    """The square structuring element of the top-hat (cached: one per mark size)."""
    return cv2.getStructuringElement(cv2.MORPH_RECT, (side, side))
