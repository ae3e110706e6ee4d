"""Rigid transforms with frame-named variables, rotation parametrisations, robot pose conventions.

The convention, stated once for the whole project
--------------------------------------------------
A transform is a 4x4 homogeneous matrix named by the frames it maps between:
``T_b_from_a`` maps a point written in frame ``a`` into frame ``b``::

    p_b = T_b_from_a @ p_a            (homogeneous column vectors)
    T_c_from_a = T_c_from_b @ T_b_from_a

Equivalently ``T_b_from_a`` is the pose of frame ``a`` expressed in frame ``b`` (its columns are
``a``'s axes and origin written in ``b``). The paper writes this as "a→b T". Lengths are millimetres
and angles degrees at every public edge unless a robot convention says otherwise (Universal Robots
uses metres and radians).

Frames: RF robot base, GF gripper/flange, CF camera, PF part (PF0 at the taught reference),
BF calibration board.

Robot conventions (``to_robot`` / ``from_robot``)
--------------------------------------------------
=========  ==========================  =====================================================
fanuc      X Y Z W P R  (mm, deg)      R = Rz(R)·Ry(P)·Rx(W)  (fixed-axis x-y-z)
yaskawa    X Y Z Rx Ry Rz (mm, deg)    same as fanuc
kuka       X Y Z A B C  (mm, deg)      R = Rz(A)·Ry(B)·Rx(C)
abb        X Y Z q1 q2 q3 q4 (mm)      unit quaternion, scalar first (w, x, y, z), q1 ≥ 0
ur         X Y Z Rx Ry Rz (m, rad)     rotation vector (axis × angle)
=========  ==========================  =====================================================

Gimbal lock: the Euler conventions lose one degree of freedom when the middle angle (P, resp. B)
is ±90°. There the first angle (W, resp. C) is set to 0 and the whole rotation about the vertical
axis is put into the last angle (R, resp. A), so the output is unique and still round-trips to the
same matrix. Away from ±90° the middle angle is returned in [-90°, 90°] and the others in
(-180°, 180°].
"""

from __future__ import annotations

from enum import StrEnum
from typing import Final

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

Array = NDArray[np.float64]

#: |cos(P)| below this is treated as gimbal lock (P = ±90° to within ~2e-8 deg).
_GIMBAL_EPS: Final = 1e-10


class RobotConvention(StrEnum):
    """How a robot controller writes a pose (see the module docstring for the formulas)."""

    FANUC = "fanuc"
    YASKAWA = "yaskawa"
    KUKA = "kuka"
    ABB = "abb"
    UR = "ur"

    @property
    def size(self) -> int:
        """Number of values in this convention's pose (7 for ABB, 6 otherwise)."""
        return 7 if self is RobotConvention.ABB else 6

    @property
    def labels(self) -> tuple[str, ...]:
        return _LABELS[self]

    @property
    def code(self) -> int:
        """Stable small integer used on the PLC interface."""
        return _CODES[self]


_LABELS: Final = {
    RobotConvention.FANUC: ("X", "Y", "Z", "W", "P", "R"),
    RobotConvention.YASKAWA: ("X", "Y", "Z", "Rx", "Ry", "Rz"),
    RobotConvention.KUKA: ("X", "Y", "Z", "A", "B", "C"),
    RobotConvention.ABB: ("X", "Y", "Z", "q1", "q2", "q3", "q4"),
    RobotConvention.UR: ("X", "Y", "Z", "Rx", "Ry", "Rz"),
}
_CODES: Final = {
    RobotConvention.FANUC: 1,
    RobotConvention.YASKAWA: 2,
    RobotConvention.KUKA: 3,
    RobotConvention.ABB: 4,
    RobotConvention.UR: 5,
}


# --------------------------------------------------------------------------- basic operations


def make_transform(R: ArrayLike, t: ArrayLike) -> Array:
    """Build a 4x4 transform from a 3x3 rotation and a translation (mm)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float).reshape(-1)
    if R.shape != (3, 3):
        raise ValueError(f"rotation must be 3x3, got shape {R.shape}")
    if t.shape != (3,):
        raise ValueError(f"translation must have 3 values, got shape {t.shape}")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def check_transform(T: ArrayLike, name: str = "transform", tol: float = 1e-6) -> Array:
    """Validate a 4x4 rigid transform at a public edge and return it as float64."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be 4x4, got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    R = T[:3, :3]
    # np.allclose's test (|a − b| ≤ atol + 1e-5·|b|) without its generic machinery, and the
    # determinant's sign as a triple product: this runs at every estimate's warm start.
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if (not (np.abs(R @ R.T - _EYE3) <= tol + _RTOL * _EYE3).all()
            or a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0):
        raise ValueError(f"{name} rotation part is not a proper rotation (R·Rᵀ ≠ I or det < 0)")
    if not (np.abs(T[3] - _LAST_ROW) <= tol + _RTOL * _LAST_ROW).all():
        raise ValueError(f"{name} last row must be [0 0 0 1], got {T[3].tolist()}")
    return T


_EYE3: Final = np.eye(3)
_LAST_ROW: Final = np.array([0.0, 0.0, 0.0, 1.0])
_RTOL: Final = 1e-5  # np.allclose's default relative tolerance, which the checks kept


def invert(T: ArrayLike) -> Array:
    """Inverse of a rigid transform: ``invert(T_b_from_a) == T_a_from_b``."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def compose(*transforms: ArrayLike) -> Array:
    """Matrix product left to right: ``compose(T_c_from_b, T_b_from_a) == T_c_from_a``."""
    if not transforms:
        return np.eye(4)
    out = np.asarray(transforms[0], dtype=float)
    for T in transforms[1:]:
        out = out @ np.asarray(T, dtype=float)
    return out


def apply(T: ArrayLike, points: ArrayLike) -> Array:
    """Map points ``["N", 3]`` (or one ``[3]`` point) from the source to the target frame."""
    T = np.asarray(T, dtype=float)
    p = np.asarray(points, dtype=float)
    if p.shape[-1] != 3:
        raise ValueError(f"points must have shape [N, 3] or [3], got {p.shape}")
    return p @ T[:3, :3].T + T[:3, 3]


# --------------------------------------------------------------------------- rotations


def rotvec_to_matrix(rotvec: ArrayLike) -> Array:
    """Rotation vector (axis × angle, radians) to 3x3 matrix."""
    return Rotation.from_rotvec(np.asarray(rotvec, dtype=float)).as_matrix()


def matrix_to_rotvec(R: ArrayLike) -> Array:
    """3x3 rotation to rotation vector (radians), angle in [0, π]."""
    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def quat_wxyz_to_matrix(q: ArrayLike) -> Array:
    """Unit quaternion (w, x, y, z) to 3x3 matrix; the quaternion is normalised first."""
    q = np.asarray(q, dtype=float).reshape(-1)
    if q.shape != (4,):
        raise ValueError(f"quaternion must have 4 values (w, x, y, z), got {q.shape}")
    n = np.linalg.norm(q)
    if not np.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {q.tolist()} has zero or non-finite norm")
    return Rotation.from_quat(q / n, scalar_first=True).as_matrix()


def matrix_to_quat_wxyz(R: ArrayLike) -> Array:
    """3x3 rotation to unit quaternion (w, x, y, z) with w ≥ 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat(scalar_first=True)
    return q if q[0] >= 0 else -q


def rotation_angle_deg(R: ArrayLike) -> float:
    """Angle of a rotation matrix in degrees (the geodesic distance from identity)."""
    R = np.asarray(R, dtype=float)
    # atan2 of sine and cosine parts: arccos alone loses half the digits near 0° (1e-6° floor).
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arctan2(s, c)))


def transform_error(T_est: ArrayLike, T_true: ArrayLike) -> tuple[float, float]:
    """Rotation (deg) and translation (mm) error between two transforms of the same frames."""
    T_est = np.asarray(T_est, dtype=float)
    T_true = np.asarray(T_true, dtype=float)
    dR = T_est[:3, :3] @ T_true[:3, :3].T
    return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))


def _rx(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a: float) -> Array:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def zyx_to_matrix(about_z_deg: float, about_y_deg: float, about_x_deg: float) -> Array:
    """R = Rz(about_z)·Ry(about_y)·Rx(about_x), angles in degrees."""
    a, b, c = np.radians([about_z_deg, about_y_deg, about_x_deg])
    return _rz(a) @ _ry(b) @ _rx(c)


def matrix_to_zyx(R: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`zyx_to_matrix`: (about_z, about_y, about_x) in degrees.

    At gimbal lock (about_y = ±90°) about_x is set to 0 and the rotation goes into about_z.
    """
    R = np.asarray(R, dtype=float)
    cos_y = float(np.hypot(R[0, 0], R[1, 0]))
    about_y = float(np.arctan2(-R[2, 0], cos_y))
    if cos_y > _GIMBAL_EPS:
        about_x = float(np.arctan2(R[2, 1], R[2, 2]))
        about_z = float(np.arctan2(R[1, 0], R[0, 0]))
    else:
        about_x = 0.0
        about_z = float(np.arctan2(-R[0, 1], R[1, 1]))
    return float(np.degrees(about_z)), float(np.degrees(about_y)), float(np.degrees(about_x))


# --------------------------------------------------------------------------- robot conventions


def to_robot(T: ArrayLike, convention: RobotConvention | str) -> Array:
    """Write a transform (mm) as the pose vector of a robot convention."""
    conv = RobotConvention(convention)
    T = np.asarray(T, dtype=float)
    t = T[:3, 3]
    R = T[:3, :3]
    if conv in (RobotConvention.FANUC, RobotConvention.YASKAWA):
        rz, ry, rx = matrix_to_zyx(R)
        return np.array([*t, rx, ry, rz])
    if conv is RobotConvention.KUKA:
        a, b, c = matrix_to_zyx(R)
        return np.array([*t, a, b, c])
    if conv is RobotConvention.ABB:
        return np.array([*t, *matrix_to_quat_wxyz(R)])
    # Universal Robots: metres and a rotation vector in radians.
    return np.array([*(t / 1000.0), *matrix_to_rotvec(R)])


def from_robot(values: ArrayLike, convention: RobotConvention | str) -> Array:
    """Build a transform (mm) from a robot convention's pose vector."""
    conv = RobotConvention(convention)
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.shape != (conv.size,):
        raise ValueError(
            f"a {conv.value} pose has {conv.size} values {conv.labels}, got {v.shape[0]}"
        )
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{conv.value} pose contains NaN or infinite values: {v.tolist()}")
    if conv in (RobotConvention.FANUC, RobotConvention.YASKAWA):
        w, p, r = v[3:]
        return make_transform(zyx_to_matrix(r, p, w), v[:3])
    if conv is RobotConvention.KUKA:
        a, b, c = v[3:]
        return make_transform(zyx_to_matrix(a, b, c), v[:3])
    if conv is RobotConvention.ABB:
        return make_transform(quat_wxyz_to_matrix(v[3:]), v[:3])
    return make_transform(rotvec_to_matrix(v[3:]), v[:3] * 1000.0)


def xyzwpr_to_matrix(values: ArrayLike) -> Array:
    """Shorthand for ``from_robot(values, "fanuc")``: X Y Z (mm), W P R (deg)."""
    return from_robot(values, RobotConvention.FANUC)


def matrix_to_xyzwpr(T: ArrayLike) -> Array:
    """Shorthand for ``to_robot(T, "fanuc")``."""
    return to_robot(T, RobotConvention.FANUC)
