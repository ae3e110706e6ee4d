"""Find mark candidates in an image region and measure each one to sub-pixel accuracy.

Candidates: a morphological top-hat (flattens illumination and panel edges) thresholded by Otsu,
external contours, area and rough-shape filters, on a reduced image.
Measurement: rays from the candidate's centre cross the mark's rim; on each ray the edge point is
where the grey profile crosses the middle between the ray's own inner and outer levels (so an
illumination gradient does not pull the edge), and an ellipse is fitted to the edge points.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mvpose_core.detect.geometry import Ellipse, fit_ellipse
from mvpose_core.transforms import Array

_STEP = 0.5  # px between samples along a ray
_LEVEL_SAMPLES = 3  # samples at each end of a ray that give its inner and outer grey levels


@dataclass(frozen=True)
class Candidate:
    """A blob that may be a mark: a rough ellipse from its contour (full-resolution pixels)."""

    ellipse: Ellipse
    area_px: float


@dataclass(frozen=True)
class Measurement:
    """A measured mark: fitted ellipse and quality figures, or the reason it failed."""

    ellipse: Ellipse | None
    reason: str | None
    contrast: float
    fit_residual_px: float
    edge_points: int


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
        # Linear (2x2 average) rather than area resampling: 5x cheaper, and only candidates
        # are looked for here; the measurement uses full-resolution pixels.
        roi = cv2.resize(roi[: h * scale, : w * scale], (w, h), interpolation=cv2.INTER_LINEAR)
    r_lo, r_hi = radius_range[0] / scale, radius_range[1] / scale
    # Black (white) top-hat: closing with a square too big to fit inside a mark erases the marks
    # and keeps what is larger (panel edges, illumination, big holes); the difference is the marks.
    side = int(np.ceil(2.0 * r_hi)) + 3
    if side >= min(roi.shape):
        return []
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (side, side))
    hat = cv2.morphologyEx(roi, cv2.MORPH_BLACKHAT if dark else cv2.MORPH_TOPHAT, kernel)
    otsu, _ = cv2.threshold(hat, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    level = max(0.5 * min_contrast, otsu)
    if hat.max() <= level:
        return []
    _, binary = cv2.threshold(hat, level, 255, cv2.THRESH_BINARY)
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
        centre = np.array([cx, cy]) * scale + (scale - 1) / 2.0 + np.array([u0, v0])
        out.append(Candidate(Ellipse(centre, a * scale, b * scale, float(angle)), area * scale * scale))
        if len(out) >= max_candidates:
            break
    return out


def _sample(image: np.ndarray, u: Array, v: Array) -> Array:
    """Bilinear grey values at float pixel positions (all inside the image)."""
    iu = np.floor(u).astype(np.intp)
    iv = np.floor(v).astype(np.intp)
    fu = u - iu
    fv = v - iv
    f = np.float64
    p00, p01 = image[iv, iu].astype(f), image[iv, iu + 1].astype(f)
    p10, p11 = image[iv + 1, iu].astype(f), image[iv + 1, iu + 1].astype(f)
    top = p00 + fu * (p01 - p00)
    bottom = p10 + fu * (p11 - p10)
    return top + fv * (bottom - top)


def measure(
    image: np.ndarray,
    start: Ellipse,
    dark: bool,
    min_contrast: float,
    max_fit_residual_px: float,
    min_edge_fraction: float,
    search_px: float,
    passes: int = 2,
) -> Measurement:
    """Sub-pixel edge points on rays from ``start`` and the ellipse through them."""
    ell = start
    contrast, residual, n_pts = 0.0, float("nan"), 0
    for k in range(passes):
        n_rays = int(np.clip(2.0 * np.pi * ell.radius, 24, 192))
        phi = np.linspace(0.0, 2.0 * np.pi, n_rays, endpoint=False)
        r_phi = ell.radius_towards(phi)
        half = search_px if k == 0 else 2.5
        t = np.arange(-half, half + 1e-9, _STEP)
        radii = np.maximum(r_phi[:, None] + t[None, :], 0.0)  # [rays, samples]
        u = ell.centre[0] + radii * np.cos(phi)[:, None]
        v = ell.centre[1] + radii * np.sin(phi)[:, None]
        H, W = image.shape
        inside = (u.min(axis=1) >= 0) & (v.min(axis=1) >= 0) & (u.max(axis=1) < W - 1) & (v.max(axis=1) < H - 1)
        if inside.mean() < min_edge_fraction:
            return Measurement(None, "at image border", contrast, residual, n_pts)
        prof = _sample(image, u[inside], v[inside])
        if not dark:
            prof = -prof  # the same code then finds light marks on a dark surface
        inner = prof[:, :_LEVEL_SAMPLES].mean(axis=1)
        outer = prof[:, -_LEVEL_SAMPLES:].mean(axis=1)
        contrast = float(np.median(outer - inner))
        if contrast < min_contrast:
            return Measurement(None, "low contrast", contrast, residual, n_pts)
        level = 0.5 * (inner + outer)
        above = prof >= level[:, None]
        # Upward crossings (inside -> outside) between samples j and j+1; keep the one nearest
        # the expected rim so a nearby edge of something else does not capture the ray.
        up = ~above[:, :-1] & above[:, 1:]
        good_ray = up.any(axis=1) & (outer - inner > 0.5 * contrast)
        centre_idx = (len(t) - 1) / 2.0
        dist = np.where(up, np.abs(np.arange(len(t) - 1)[None, :] + 0.5 - centre_idx), np.inf)
        j = np.argmin(dist, axis=1)
        rows = np.arange(prof.shape[0])
        p0, p1 = prof[rows, j], prof[rows, j + 1]
        frac = (level - p0) / np.where(p1 != p0, p1 - p0, 1.0)
        edge_r = radii[inside][rows, j] + _STEP * np.clip(frac, 0.0, 1.0)
        good_ray &= np.isfinite(edge_r)
        n_pts = int(good_ray.sum())
        if n_pts < min_edge_fraction * n_rays:
            return Measurement(None, "incomplete edge", contrast, residual, n_pts)
        ph = phi[inside][good_ray]
        pts = ell.centre + edge_r[good_ray, None] * np.stack([np.cos(ph), np.sin(ph)], axis=1)
        fitted = fit_ellipse(pts)
        if fitted is None:
            return Measurement(None, "shape", contrast, residual, n_pts)
        residual = float(np.sqrt(np.mean(fitted.distances(pts) ** 2)))
        ell = fitted
        if residual > max_fit_residual_px and k == passes - 1:
            return Measurement(None, "shape", contrast, residual, n_pts)
    return Measurement(ell, None, contrast, residual, n_pts)
