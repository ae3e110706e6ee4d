"""Ellipses: the imaged rim of a circular mark, sampled in 3D and fitted as the detector fits one.

:class:`Ellipse` (one) and :class:`Ellipses` (a batch, arrays), the weighted algebraic conic fit
(:func:`fit_ellipses`, batched over marks; the detector fits its edge points with it, the
prediction and the perspective correction their projected rims), and the rim of a circle of
given centre, normal and radius as 3D points (:func:`rims`, :func:`rim_points`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mvpose_core.scene import ProjectedMark
from mvpose_core.transforms import Array

_RIM_SAMPLES = 72


@lru_cache(maxsize=8)
def _cos_sin(n: int) -> Array:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    cs = np.stack([np.cos(t), np.sin(t)], axis=1)
    cs.flags.writeable = False
    return cs


@dataclass(frozen=True)
class Ellipse:
    """Centre (px), semi-axes (px, a ≥ b) and the angle of the major axis (rad, from +u)."""

    centre: Array
    a: float
    b: float
    angle: float

    @property
    def radius(self) -> float:
        return float(np.sqrt(self.a * self.b))

    @property
    def axis_ratio(self) -> float:
        return self.b / self.a

    def radius_towards(self, phi: Array) -> Array:
        """Distance from the centre to the ellipse along directions ``phi`` (rad)."""
        d = phi - self.angle
        return self.a * self.b / np.hypot(self.b * np.cos(d), self.a * np.sin(d))

    def distances(self, pts: Array) -> Array:
        """Approximate signed distances (px, + outside) of points ``["N", 2]`` to the ellipse."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        dx, dy = pts[:, 0] - self.centre[0], pts[:, 1] - self.centre[1]
        x, y = c * dx + s * dy, -s * dx + c * dy
        q = np.sqrt((x / self.a) ** 2 + (y / self.b) ** 2) + 1e-12
        grad = np.sqrt((x / self.a**2) ** 2 + (y / self.b**2) ** 2) / q + 1e-12
        return (q - 1.0) / grad


@dataclass(frozen=True)
class Ellipses:
    """A batch of ellipses as arrays: centres ``["C", 2]``, semi-axes and angles ``["C"]``."""

    centre: Array
    a: Array
    b: Array
    angle: Array
    valid: Array | None = None  # which fits succeeded (None: all)

    @classmethod
    def of(cls, items: list[Ellipse]) -> Ellipses:
        return cls(
            np.array([e.centre for e in items], dtype=float),
            np.array([e.a for e in items], dtype=float),
            np.array([e.b for e in items], dtype=float),
            np.array([e.angle for e in items], dtype=float),
        )

    def __getitem__(self, k: int) -> Ellipse:
        return Ellipse(
            self.centre[k].copy(), float(self.a[k]), float(self.b[k]), float(self.angle[k])
        )

    @property
    def radius(self) -> Array:
        return np.sqrt(self.a * self.b)

    @property
    def ok(self) -> np.ndarray:
        """``["C"]`` bool: which fits succeeded."""
        return np.ones(len(self.a), dtype=bool) if self.valid is None else self.valid

    def radius_towards(self, phi: Array) -> Array:
        """``["C", "R"]`` distances from each centre to its ellipse along directions ``phi``
        (``["R"]`` for all, or ``["C", "R"]``)."""
        d = (phi if phi.ndim == 2 else phi[None, :]) - self.angle[:, None]
        a, b = self.a[:, None], self.b[:, None]
        return a * b / np.hypot(b * np.cos(d), a * np.sin(d))

    def distances(self, pts: Array) -> Array:
        """Approximate signed distances ``["C", "N"]`` of points ``["C", "N", 2]`` (+ outside)."""
        c, s = np.cos(self.angle)[:, None], np.sin(self.angle)[:, None]
        dx, dy = pts[..., 0] - self.centre[:, 0, None], pts[..., 1] - self.centre[:, 1, None]
        x, y = c * dx + s * dy, -s * dx + c * dy
        a, b = self.a[:, None], self.b[:, None]
        q = np.sqrt((x / a) ** 2 + (y / b) ** 2) + 1e-12
        grad = np.sqrt((x / a**2) ** 2 + (y / b**2) ** 2) / q + 1e-12
        return (q - 1.0) / grad


_EYE5 = np.eye(5)


def fit_ellipses(pts: Array, weights: Array) -> Ellipses:
    """Least-squares conics through point sets ``["C", "N", 2]`` with weights ``["C", "N"]``.

    Each set is centred and scaled first, then ``A x² + B xy + C y² + D x + E y = 1`` is solved
    by its 5 × 5 normal equations, all sets in one batched solve. For closed rims with sub-pixel
    noise the algebraic fit's bias is O(σ²/r), far below the noise; sets that give no real
    ellipse come back with ``valid`` False.
    """
    # Sums over the points are products with the weights (matmul), not np.add.reduce over the
    # middle axis of small 3-D arrays, which is ~3x slower there (this runs in every measuring
    # pass); the same numbers up to rounding.
    C, P = weights.shape
    w = weights.astype(float)
    wr = w[:, None, :]  # [C, 1, N]
    count = np.add.reduce(w, axis=1)
    n = np.maximum(count, 1.0)
    mean = np.matmul(wr, pts)[:, 0, :] / n[:, None]
    d = pts - mean[:, None, :]
    scale = np.sqrt(np.add.reduce(np.matmul(wr, d * d)[:, 0, :], axis=1) / n) + 1e-12
    inv = 1.0 / scale[:, None]
    x, y = d[..., 0] * inv, d[..., 1] * inv
    M = np.empty((C, 5, P))  # the conic's monomials per point, [C, 5, N]
    np.multiply(x, x, out=M[:, 0])
    np.multiply(x, y, out=M[:, 1])
    np.multiply(y, y, out=M[:, 2])
    M[:, 3] = x
    M[:, 4] = y
    Mw = M * wr
    N = np.matmul(Mw, M.transpose(0, 2, 1)) + 1e-12 * _EYE5
    rhs = np.add.reduce(Mw, axis=2)
    valid = count >= 6
    try:
        p = np.linalg.solve(N, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        p = np.zeros((len(pts), 5))
        valid = np.zeros(len(pts), dtype=bool)
    A, B, Cc, D, E = p.T
    det = 4.0 * A * Cc - B * B
    valid &= det > 1e-12
    det = np.where(valid, det, 1.0)
    x0 = (B * E - 2.0 * Cc * D) / det
    y0 = (B * D - 2.0 * A * E) / det
    k = 1.0 - 0.5 * (
        D * x0 + E * y0
    )  # (p - c)^T Q (p - c) = k at the rim, Q = [[A, B/2], [B/2, C]]
    # Eigenvalues of Q in closed form; the smaller one belongs to the major axis.
    mid, rad = 0.5 * (A + Cc), np.hypot(0.5 * (A - Cc), 0.5 * B)
    lam_small, lam_big = mid - rad, mid + rad
    valid &= (lam_small > 0) & (k > 0)
    lam_small = np.where(valid, lam_small, 1.0)
    lam_big = np.where(valid, lam_big, 1.0)
    k = np.where(valid, k, 1.0)
    a = np.sqrt(k / lam_small) * scale
    b = np.sqrt(k / lam_big) * scale
    angle = 0.5 * np.arctan2(B, A - Cc) + 0.5 * np.pi  # atan2 gives the minor axis' direction
    centre = mean
    centre[:, 0] += x0 * scale
    centre[:, 1] += y0 * scale
    return Ellipses(centre, a, b, angle, valid)


def fit_ellipse(pts: Array) -> Ellipse | None:
    """The least-squares ellipse through ``["N", 2]`` points (:func:`fit_ellipses` for one set)."""
    if pts.shape[0] < 6:
        return None
    e = fit_ellipses(pts[None].astype(float), np.ones((1, pts.shape[0])))
    return e[0] if bool(e.ok[0]) else None


def rim_points(pm: ProjectedMark, radius_mm: float, n: int = _RIM_SAMPLES) -> Array:
    """``n`` points ``["n", 3]`` (camera frame) evenly spaced on the rim of the mark's circle."""
    return rims(pm.p_cf[None], pm.n_cf[None], radius_mm, n)[0]


def rims(p_cf: Array, n_cf: Array, radius_mm: float | Array, n: int = _RIM_SAMPLES) -> Array:
    """:func:`rim_points` of marks at ``p_cf`` ``["M", 3]`` with unit normals ``n_cf`` and radii
    ``radius_mm`` (one for all, or ``["M"]``): ``["M", "n", 3]``."""
    nx, ny, nz = n_cf[:, 0:1], n_cf[:, 1:2], n_cf[:, 2:3]
    zero = np.zeros_like(nx)
    # e1 = n × (x or y axis), e2 = n × e1: an orthonormal basis of the mark's plane.
    e1 = np.where(
        np.abs(nx) < 0.9,
        np.concatenate([zero, nz, -ny], axis=1),
        np.concatenate([-nz, zero, nx], axis=1),
    )
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.concatenate(  # n × e1
        [ny * e1[:, 2:3] - nz * e1[:, 1:2], nz * e1[:, 0:1] - nx * e1[:, 2:3],
         nx * e1[:, 1:2] - ny * e1[:, 0:1]],
        axis=1,
    )
    cs = _cos_sin(n)
    r = np.broadcast_to(np.asarray(radius_mm, dtype=float), (p_cf.shape[0],))[:, None, None]
    return p_cf[:, None, :] + r * (
        cs[None, :, :1] * e1[:, None, :] + cs[None, :, 1:] * e2[:, None, :]
    )
