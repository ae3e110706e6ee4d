"""Pose uncertainty: information matrix and Cramér–Rao covariance, moved to any frame on the part.

All covariances are 6x6 over δ = (ω [rad], v [mm]), the right perturbation of ``T_rf_from_pf``
in the part frame (see :mod:`mvpose_core.refine`): ω is the rotation error about PF's axes and v
the error of PF's origin written in PF. :func:`covariance_in_frame` moves it to another frame
rigid to the part (the grasp frame), where the lever arm turns rotation into translation.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dsyevd

from mvpose_core.problem import pack_layout
from mvpose_core.refine import Array, residuals_and_jacobian
from mvpose_core.scene import ViewCamera
from mvpose_core.transforms import check_transform

#: one entry of an observation layout: (view, camera_id, mark_id)
LayoutEntry = tuple[int, str, str]


def information_from_jacobian(J: Array) -> Array:
    """JᵀJ for a whitened Jacobian ``[N, 2, 6]`` (rows already divided by σ)."""
    Jf = J.reshape(-1, 6)
    return Jf.T @ Jf


def pose_information(
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    layout: Sequence[LayoutEntry],
    T_rf_from_pf: np.ndarray,
    sigma_px: float = 1.0,
    objective: Literal["all", "left_only"] = "all",
) -> Array:
    """Fisher information (6x6) of the pose for observations ``layout`` with σ px per coordinate.

    ``objective="left_only"`` keeps the observations of each rig's first camera (the paper's
    eq. 15). Raises ``ValueError`` naming the camera and mark if a mark is behind a camera.
    """
    T = check_transform(T_rf_from_pf, "T_rf_from_pf")
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise ValueError(f"sigma_px must be a positive number of pixels, got {sigma_px}")
    pk, rows = pack_layout(cameras, marks_pf, layout, objective)
    pk = replace(pk, weight=np.full(pk.n, 1.0 / sigma_px))
    _, J, depth = residuals_and_jacobian(pk, T[:3, :3], T[:3, 3])
    bad = np.flatnonzero(~(depth > 0))
    if bad.size:
        v, cam, mark = layout[rows[bad[0]]]
        raise ValueError(
            f"mark {mark!r} is behind camera v{v}/{cam} (depth {depth[bad[0]]:.1f} mm)"
        )
    return information_from_jacobian(J / sigma_px)


def cramer_rao_covariance(
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    layout: Sequence[LayoutEntry],
    T_rf_from_pf: np.ndarray,
    sigma_px: float = 1.0,
    objective: Literal["all", "left_only"] = "all",
) -> Array:
    """Cramér–Rao bound (6x6 covariance of δ = (ω, v)) for an unbiased pose estimate.

    Raises ``ValueError`` when the layout does not determine all six degrees of freedom.
    """
    info = pose_information(cameras, marks_pf, layout, T_rf_from_pf, sigma_px, objective)
    return invert_information(info)


def invert_information(info: Array) -> Array:
    """Covariance from an information matrix; ``ValueError`` if a direction is unobservable."""
    # Scale rotation against translation before judging conditioning (rad vs mm differ by ~1e3).
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    normed = info / np.outer(d, d)
    # One decomposition gives the conditioning and the inverse (LAPACK directly: numpy's
    # wrapper costs as much as the 6x6 decomposition itself).
    condition = "inf"
    if np.isfinite(normed).all():
        ev, V, code = dsyevd(normed)
        if code == 0 and ev[0] >= 1e-10 * ev[-1]:
            return ((V / ev) @ V.T) / np.outer(d, d)
        if code == 0:
            condition = f"{ev[-1] / max(ev[0], 1e-300):.1e}"
    raise ValueError(
        "the observations do not determine the pose: the information matrix is singular "
        f"(condition {condition}); add marks or cameras"
    )


def adjoint(T_b_from_a: NDArray[np.floating[Any]]) -> Array:
    """6x6 adjoint: a right perturbation (ω, v) of frame a becomes one of frame b."""
    R = T_b_from_a[:3, :3]
    t = T_b_from_a[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = tx @ R
    return Ad


def covariance_in_frame(cov_pf: Array, T_pf_from_g: Array) -> Array:
    """Covariance of the perturbation of frame g (rigid to the part) from the one of PF."""
    Ad = adjoint(np.linalg.inv(T_pf_from_g))
    return Ad @ cov_pf @ Ad.T


def sigma_figures(cov: Array) -> tuple[float, float]:
    """1σ rotation (deg) and translation (mm): RMS magnitudes √trace of each 3x3 block.

    √trace is the RMS length of the error vector (what a Monte Carlo RMS error measures);
    it is at least the largest per-axis σ, so a gate on it is conservative.
    """
    rot = float(np.degrees(np.sqrt(max(np.trace(cov[:3, :3]), 0.0))))
    trans = float(np.sqrt(max(np.trace(cov[3:, 3:]), 0.0)))
    return rot, trans
