"""Triangulation of marks seen by two or more cameras, from undistorted viewing rays.

Each observation is a ray in the robot base frame RF (camera centre + unit direction of the
undistorted pixel). A mark seen by several cameras (both cameras of a stereo rig, or several
views) is placed at the point that minimises the sum of squared perpendicular distances to its
rays — the midpoint method, generalised to any number of rays; for two rays it is the midpoint
of their common perpendicular. It is the starting point of the pose estimate, not the estimate:
the refinement works on the reprojection error.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from mvpose_core.refine import Array

#: Rays closer to parallel than this (rad) do not triangulate a point (depth is unobservable).
MIN_RAY_ANGLE_RAD = np.radians(0.5)


def group_matrix(group: NDArray[np.intp], n_groups: int) -> Array:
    """``[K, N]`` one-hot rows: entry (k, i) is 1 where ray i belongs to group k."""
    return (group[None, :] == np.arange(n_groups)[:, None]).astype(float)


_EYE3 = np.eye(3)
#: For two rays at angle θ, Σ(I − d dᵀ) has eigenvalues 1 − cos θ, 1 + cos θ and 2, so its
#: determinant is 2 sin²θ; more rays only add to it. Below this, depth is unobservable.
_MIN_DET = 2.0 * float(np.sin(MIN_RAY_ANGLE_RAD)) ** 2


def rays_intersection(
    centres: Array, directions: Array, group: NDArray[np.intp], n_groups: int,
    onehot: Array | None = None,
) -> tuple[Array, NDArray[np.bool_]]:
    """Least-squares intersection of the rays of each group.

    ``centres``/``directions`` are ``[N, 3]`` (unit directions); ``group[i]`` in ``[0, n_groups)``
    says which point ray ``i`` belongs to (``onehot``: its :func:`group_matrix`, if the caller
    keeps one). Returns points ``[n_groups, 3]`` and a mask of groups with at least two rays
    that are not near-parallel (others hold NaN).
    """
    # Sum per group with a one-hot matrix product (much cheaper than np.add.at for small N).
    if onehot is None:
        onehot = group_matrix(group, n_groups)
    P = _EYE3 - directions[:, :, None] * directions[:, None, :]  # [N, 3, 3] I − d dᵀ
    A = (onehot @ P.reshape(-1, 9)).reshape(n_groups, 3, 3)
    b = onehot @ (P @ centres[:, :, None])[:, :, 0]
    # One ray (or none) gives a singular A, so its determinant test fails too.
    ok = np.linalg.det(A) > _MIN_DET
    # Groups that fail solve an identity system and are then set to NaN: one batched solve.
    x = np.linalg.solve(np.where(ok[:, None, None], A, _EYE3), b[:, :, None])[:, :, 0]
    return np.where(ok[:, None], x, np.nan), ok


@dataclass(frozen=True)
class Triangulated:
    """Marks triangulated from two or more rays, in RF, with their reprojection residuals."""

    mark_ids: tuple[str, ...]
    points_rf: Array  # [K, 3] mm
    residual_px: Array  # [K] RMS reprojection error over the mark's observations, px
    n_rays: NDArray[np.intp]  # [K]


def triangulate_marks(observations: Sequence, cameras: Sequence) -> Triangulated:
    """Triangulate every mark that two or more cameras (of any views) observe.

    ``observations`` are :class:`mvpose_core.estimate.Observation`, ``cameras`` the
    :class:`mvpose_core.scene.ViewCamera` they refer to. Marks with one ray, or only
    near-parallel rays, are left out.
    """
    by_key = {(c.view, c.camera_id): c for c in cameras}
    ids = sorted({o.mark_id for o in observations})
    index = {m: i for i, m in enumerate(ids)}
    centres, dirs, group, cams = [], [], [], []
    for o in observations:
        cam = by_key.get((o.view, o.camera_id))
        if cam is None:
            raise ValueError(f"observation names unknown camera v{o.view}/{o.camera_id}")
        ray_cf = cam.model.bearing(np.asarray(o.uv, dtype=float).reshape(1, 2))[0]
        centres.append(cam.T_rf_from_cf[:3, 3])
        dirs.append(cam.T_rf_from_cf[:3, :3] @ ray_cf)
        group.append(index[o.mark_id])
        cams.append(cam)
    g = np.asarray(group, dtype=np.intp)
    points, ok = rays_intersection(np.asarray(centres), np.asarray(dirs), g, len(ids))
    sq = np.zeros(len(ids))
    for o, cam, gi in zip(observations, cams, g, strict=True):
        if ok[gi]:
            T_cf_from_rf = np.linalg.inv(cam.T_rf_from_cf)
            p_cf = T_cf_from_rf[:3, :3] @ points[gi] + T_cf_from_rf[:3, 3]
            sq[gi] += float(np.sum((cam.model.project(p_cf[None])[0] - np.asarray(o.uv)) ** 2))
    counts = np.bincount(g, minlength=len(ids))
    keep = np.flatnonzero(ok)
    return Triangulated(
        mark_ids=tuple(ids[i] for i in keep),
        points_rf=points[keep],
        residual_px=np.sqrt(sq[keep] / counts[keep]),
        n_rays=counts[keep],
    )
