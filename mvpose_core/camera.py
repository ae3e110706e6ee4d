"""Pinhole camera with OpenCV lens distortion: projection, its analytic Jacobian, undistortion.

The model is OpenCV's (``cv2.projectPoints``) with up to eight coefficients
``k1 k2 p1 p2 [k3 [k4 k5 k6]]`` (radial rational model and tangential terms); thin-prism and
tilted-sensor terms are not supported. Points are in the camera frame CF in mm, z forward;
pixels have (0, 0) at the centre of the top-left pixel, as in OpenCV.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

_NO_MOTION = np.zeros(3)  # rvec and tvec of cv2.projectPoints: the points are in CF already
_NO_MOTION.flags.writeable = False
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics, distortion and image size of one camera."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    _k: tuple[float, ...] = field(init=False, repr=False, compare=False)
    #: K and the eight coefficients as arrays for cv2.projectPoints, read-only
    _cv: tuple[Array, Array] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"camera {name} must be a positive focal length in px, got {v}")
        if not (np.isfinite(self.cx) and np.isfinite(self.cy)):
            raise ValueError(f"camera principal point must be finite, got ({self.cx}, {self.cy})")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if len(self.dist) not in (4, 5, 8):
            raise ValueError(
                f"distortion needs 4, 5 or 8 coefficients (k1 k2 p1 p2 [k3 [k4 k5 k6]]), "
                f"got {len(self.dist)}"
            )
        if not all(np.isfinite(self.dist)):
            raise ValueError(f"distortion coefficients must be finite, got {list(self.dist)}")
        k = tuple(float(x) for x in self.dist) + (0.0,) * (8 - len(self.dist))
        object.__setattr__(self, "_k", k)
        K = np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        d = np.array(k)
        K.flags.writeable = d.flags.writeable = False
        object.__setattr__(self, "_cv", (K, d))

    # ------------------------------------------------------------------ OpenCV interop
    @property
    def K(self) -> Array:
        """3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> Array:
        return np.asarray(self.dist, dtype=float)

    @property
    def has_distortion(self) -> bool:
        return any(v != 0.0 for v in self.dist)

    # ------------------------------------------------------------------ projection
    def distort_normalized(self, xy: Array) -> Array:
        """Apply lens distortion to normalised coordinates ``["N", 2]`` (x = X/Z, y = Y/Z)."""
        k1, k2, p1, p2, k3, k4, k5, k6 = self._k
        x = xy[:, 0]
        y = xy[:, 1]
        r2 = x * x + y * y
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = num / den
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, p_cf: ArrayLike) -> Array:
        """Project points ``["N", 3]`` in the camera frame to distorted pixels ``["N", 2]``.

        Points must be in front of the camera (z > 0); callers at the public edge check it
        (see :func:`check_in_front`). Matches ``cv2.projectPoints`` to floating-point precision.
        """
        p = np.ascontiguousarray(p_cf, dtype=float).reshape(-1, 3)
        if p.shape[0] == 0:
            return np.empty((0, 2))
        # One OpenCV call: the same model, a few µs instead of a few tens for numpy's steps.
        uv, _ = cv2.projectPoints(p, _NO_MOTION, _NO_MOTION, *self._cv)
        return np.asarray(uv, dtype=np.float64).reshape(-1, 2)

    def project_with_jacobian(self, p_cf: ArrayLike) -> tuple[Array, Array]:
        """Pixels ``["N", 2]`` and their Jacobian ``["N", 2, 3]`` with respect to the 3D point."""
        p = np.asarray(p_cf, dtype=float).reshape(-1, 3)
        X, Y, Z = p[:, 0], p[:, 1], p[:, 2]
        iz = 1.0 / Z
        x = X * iz
        y = Y * iz
        k1, k2, p1, p2, k3, k4, k5, k6 = self._k
        r2 = x * x + y * y
        num = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        den = 1.0 + r2 * (k4 + r2 * (k5 + r2 * k6))
        dnum = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)  # d num / d r2
        dden = k4 + r2 * (2.0 * k5 + 3.0 * k6 * r2)
        radial = num / den
        drad = (dnum * den - num * dden) / (den * den)  # d radial / d r2
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        # d(xd, yd) / d(x, y); d r2/dx = 2x, d r2/dy = 2y
        dxd_dx = radial + x * drad * 2.0 * x + 2.0 * p1 * y + p2 * 6.0 * x
        dxd_dy = x * drad * 2.0 * y + 2.0 * p1 * x + p2 * 2.0 * y
        dyd_dx = y * drad * 2.0 * x + p1 * 2.0 * x + 2.0 * p2 * y
        dyd_dy = radial + y * drad * 2.0 * y + p1 * 6.0 * y + 2.0 * p2 * x
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)
        # d(x, y) / d(X, Y, Z) = [[1/Z, 0, -x/Z], [0, 1/Z, -y/Z]]
        J = np.empty((p.shape[0], 2, 3))
        J[:, 0, 0] = self.fx * dxd_dx * iz
        J[:, 0, 1] = self.fx * dxd_dy * iz
        J[:, 0, 2] = -self.fx * (dxd_dx * x + dxd_dy * y) * iz
        J[:, 1, 0] = self.fy * dyd_dx * iz
        J[:, 1, 1] = self.fy * dyd_dy * iz
        J[:, 1, 2] = -self.fy * (dyd_dx * x + dyd_dy * y) * iz
        return uv, J

    # ------------------------------------------------------------------ undistortion
    def undistort_normalized(self, uv: ArrayLike) -> Array:
        """Distorted pixels ``["N", 2]`` to ideal normalised coordinates (x = X/Z, y = Y/Z)."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        if not self.has_distortion:
            return np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], 1)
        # OpenCV's stubs want R and P even though None (identity, normalised output) is valid.
        out = cv2.undistortPointsIter(  # type: ignore[call-overload]
            uv.reshape(-1, 1, 2), self.K, self.dist_array, None, None, _UNDISTORT_CRITERIA
        )
        return out.reshape(-1, 2).astype(float)

    def undistort_pixels(self, uv: ArrayLike) -> Array:
        """Distorted pixels to the pixels an ideal (distortion-free) pinhole would see."""
        xy = self.undistort_normalized(uv)
        return np.stack([self.fx * xy[:, 0] + self.cx, self.fy * xy[:, 1] + self.cy], axis=1)

    def bearing(self, uv: ArrayLike) -> Array:
        """Unit viewing rays ``["N", 3]`` in the camera frame for distorted pixels."""
        xy = self.undistort_normalized(uv)
        rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def in_image(self, uv: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """Which pixels lie inside the image, at least ``margin`` px from the border."""
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        return (
            (uv[:, 0] >= -0.5 + margin)
            & (uv[:, 0] <= self.width - 0.5 - margin)
            & (uv[:, 1] >= -0.5 + margin)
            & (uv[:, 1] <= self.height - 0.5 - margin)
        )


def check_in_front(p_cf: Array, what: str, min_depth_mm: float = 1.0) -> None:
    """Raise ``ValueError`` naming ``what`` if any point is behind or on the camera plane."""
    z = np.asarray(p_cf, dtype=float).reshape(-1, 3)[:, 2]
    bad = np.flatnonzero(~(z > min_depth_mm))
    if bad.size:
        raise ValueError(
            f"{what}: point {int(bad[0])} is behind the camera (z = {float(z[bad[0]]):.1f} mm)"
        )
