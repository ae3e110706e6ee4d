"""Pose uncertainty: information matrix and Cramér–Rao covariance, moved to any frame on the part;
the detector noise estimated from the residuals, and the calibration's covariance propagated.

All covariances are 6x6 over δ = (ω [rad], v [mm]), the right perturbation of ``T_rf_from_pf``
in the part frame (see :mod:`mvpose_core.refine`): ω is the rotation error about PF's axes and v
the error of PF's origin written in PF. :func:`covariance_in_frame` moves it to another frame
rigid to the part (the grasp frame), where the lever arm turns rotation into translation.

The two parts of a measurement's uncertainty (docs/engine.md, "Uncertainty model"):

- detector: the pose covariance at the weights 1/σ scaled by :func:`detector_scale`, the
  variance factor estimated from the weighted residuals with 2N − 6 degrees of freedom, pooled
  with the a-priori σ (the recipe's ``detector_noise_px``) as ``detector_prior_dof`` pseudo
  degrees of freedom;
- calibration: every uncertain transform of the camera chain (:func:`calibration_terms`: flange
  pose per view, hand-eye or fixed rig pose, camera in its rig) is a right perturbation ε with a
  covariance; it moves each camera it carries by ``Ad(S⁻¹)·ε``, which moves the predicted pixels
  by K·ε; the pose absorbs ``(JᵀWJ)⁻¹ JᵀW K ε`` of it (:func:`calibration_covariance`: first
  order, through the estimator's own Jacobian J and weights W). Terms are independent.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dsyevd

from mvpose_core.cache import IdentityCache
from mvpose_core.problem import Observation, pack_layout
from mvpose_core.refine import Array, residuals_and_jacobian
from mvpose_core.scene import ViewCamera
from mvpose_core.station import StationConfig
from mvpose_core.transforms import check_transform, compose

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
    s = 1.0 / np.sqrt(np.maximum(np.diagonal(info), 1e-300))
    S = s[:, None] * s
    normed = info * S
    # One decomposition gives the conditioning and the inverse (LAPACK directly: numpy's
    # wrapper costs as much as the 6x6 decomposition itself). The sum is finite only if every
    # entry is (normed entries are within ±1 for an information matrix, so it cannot overflow).
    condition = "inf"
    if math.isfinite(float(np.add.reduce(normed, axis=None))):
        ev, V, code = dsyevd(normed)
        if code == 0 and ev[0] >= 1e-10 * ev[-1]:
            return ((V / ev) @ V.T) * S
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
    return in_frame(cov_pf, frame_adjoint(T_pf_from_g))


def frame_adjoint(T_pf_from_g: Array) -> Array:
    """The 6x6 that moves a covariance of PF's perturbation to frame g's (:func:`in_frame`)."""
    return adjoint(np.linalg.inv(T_pf_from_g))


def in_frame(cov_pf: Array, Ad: Array) -> Array:
    """:func:`covariance_in_frame` with the frame's :func:`frame_adjoint` made once."""
    return Ad @ cov_pf @ Ad.T


def sigma_figures(cov: Array) -> tuple[float, float]:
    """1σ rotation (deg) and translation (mm): RMS magnitudes √trace of each 3x3 block.

    √trace is the RMS length of the error vector (what a Monte Carlo RMS error measures);
    it is at least the largest per-axis σ, so a gate on it is conservative.
    """
    d = cov.diagonal().tolist()  # the traces in np.trace's order of summation
    rot = math.degrees(math.sqrt(max(d[0] + d[1] + d[2], 0.0)))
    trans = math.sqrt(max(d[3] + d[4] + d[5], 0.0))
    return rot, trans


# ----------------------------------------------------------------------- detector part


def detector_scale(weighted_sq_sum: float, dof: int, prior_dof: float) -> float:
    """Variance factor k² of the detector σ: ``(ν₀ + Σ (r/σ)²) / (ν₀ + dof)``.

    ``weighted_sq_sum`` is the sum of squared residuals in units of their a-priori σ, ``dof``
    = 2N − 6 for N observations used; ``prior_dof`` ν₀ weighs the a-priori σ (k² = 1) as that
    many degrees of freedom. With ν₀ = 0 it is the residuals' own estimate (unbiased: E k² = the
    true factor); with no degrees of freedom at all the a-priori σ stands (k² = 1).
    """
    n = prior_dof + dof
    if not n > 0:
        return 1.0
    return float((prior_dof + weighted_sq_sum) / n)


def detector_sigmas(observations: Sequence[Observation], sigma0: float) -> list[Observation]:
    """The observations with each one's a-priori σ from its detection: ``σ0·√(v/v̄)``, ``v``
    its :attr:`~mvpose_core.problem.Observation.centre_variance` and ``v̄`` their mean over the
    trigger, so ``σ0`` stays the σ of the trigger's typical mark and :func:`detector_scale`
    still scales them all. A small or faint mark's centre is noisier than a large one's
    (rendered bonnet, 5-18 px radius: about ∝ 1/√radius), and so is one whose rim clutter
    disturbs; one σ for all would misweigh them in the pose and misstate its covariance along
    the directions the noisier centres fix (on a stereo pair: along the epipolar lines, where
    the residuals cannot see them).
    Observations with their own ``sigma_px`` keep it; when some lack a variance figure (e.g.
    synthetic observations) they are returned as given."""
    free = [o for o in observations if o.sigma_px is None]
    v = np.array([o.centre_variance if o.centre_variance is not None else np.nan for o in free])
    if not free or not np.all(np.isfinite(v) & (v > 0)):
        return list(observations)
    sigmas = iter((sigma0 / float(np.sqrt(v.mean())) * np.sqrt(v)).tolist())
    return [o if o.sigma_px is not None else o.but(sigma_px=next(sigmas)) for o in observations]


# ----------------------------------------------------------------------- calibration part


@dataclass(frozen=True)
class CalibrationTerm:
    """One uncertain transform of the station and the view cameras it carries.

    ``covariance`` is 6x6 over its right perturbation ε = (ω [rad], v [mm]); ``moves`` maps each
    (view, camera_id) it carries to the 6x6 ``Ad(S⁻¹)`` that turns ε into that camera's right
    perturbation (S = the rest of the chain from the transform to the camera).
    """

    name: str
    covariance: Array
    moves: Mapping[tuple[int, str], Array]


_TERMS: IdentityCache[tuple[CalibrationTerm, ...]] = IdentityCache(16)


def calibration_terms(
    station: StationConfig, cameras: Sequence[ViewCamera]
) -> tuple[CalibrationTerm, ...]:
    """The station's uncertain transforms with a non-zero 1σ (``station.uncertainty``),
    remembered for the very same station and camera objects (all frozen).

    Robot rig: ``T_rf_from_cf = T_rf_from_gf(view) · T_gf_from_rig · T_rig_from_cf`` — one
    robot-repeatability term per view, one hand-eye term per rig shared by every view, one term
    per camera for its place in the rig. Fixed rig: ``T_rf_from_rig · T_rig_from_cf``.
    """
    return _TERMS.get((station, *cameras), None, lambda: _calibration_terms(station, cameras))


def _calibration_terms(
    station: StationConfig, cameras: Sequence[ViewCamera]
) -> tuple[CalibrationTerm, ...]:
    u = station.uncertainty
    terms: dict[str, tuple[Array, dict[tuple[int, str], Array]]] = {}

    def add(name: str, cov: Array, key: tuple[int, str], S: Array) -> None:
        terms.setdefault(name, (cov, {}))[1][key] = adjoint(np.linalg.inv(S))

    for vc in cameras:
        rig = station.rig_of(vc.camera_id)
        rc = next(c for c in rig.cameras if c.camera == vc.camera_id)
        T_rig_from_cf = rc.T_rig_from_cf.matrix
        key = (vc.view, vc.camera_id)
        cam_sigma = u.cameras.get(vc.camera_id)
        if cam_sigma is not None and not cam_sigma.is_zero:
            add(f"camera {vc.camera_id} in rig {rig.id}", cam_sigma.covariance(), key, np.eye(4))
        rig_sigma = u.rigs.get(rig.id)
        if rig_sigma is not None and not rig_sigma.is_zero:
            what = "hand-eye" if rig.mount == "robot" else "pose of fixed rig"
            add(f"{what} {rig.id}", rig_sigma.covariance(), key, T_rig_from_cf)
        if rig.mount == "robot" and not u.robot_repeatability.is_zero:
            assert rig.T_gf_from_rig is not None  # validated
            add(f"robot pose at view {vc.view}", u.robot_repeatability.covariance(), key,
                compose(rig.T_gf_from_rig.matrix, T_rig_from_cf))
    return tuple(CalibrationTerm(name, cov, moves) for name, (cov, moves) in terms.items())


def _skew(p: Array) -> Array:
    m = np.zeros((p.shape[0], 3, 3))
    m[:, 0, 1], m[:, 0, 2] = -p[:, 2], p[:, 1]
    m[:, 1, 0], m[:, 1, 2] = p[:, 2], -p[:, 0]
    m[:, 2, 0], m[:, 2, 1] = -p[:, 1], p[:, 0]
    return m


def calibration_covariance(
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    layout: Sequence[LayoutEntry],
    weights: Array,
    T_rf_from_pf: np.ndarray,
    terms: Sequence[CalibrationTerm],
) -> tuple[Array, dict[str, Array]]:
    """Pose covariance (6x6, δ in PF) from calibration errors, in total and per term.

    ``layout`` and ``weights`` (1/σ, px⁻¹) are the observations the estimate used. First order:
    the estimate moves by ``(JᵀWJ)⁻¹ JᵀW K ε`` for a calibration error ε (module docstring).
    """
    per: dict[str, Array] = {}
    if not terms:
        return np.zeros((6, 6)), per
    T = check_transform(T_rf_from_pf, "T_rf_from_pf")
    pk, rows = pack_layout(cameras, marks_pf, layout)
    _, J, _ = residuals_and_jacobian(pk, T[:3, :3], T[:3, 3])
    w2 = np.asarray(weights, dtype=float)[rows] ** 2
    Jw2 = J * w2[:, None, None]  # [N, 2, 6]
    cov = invert_information(np.einsum("nij,nik->jk", J, Jw2))
    A = pk.R_cf_from_rf @ T[:3, :3]  # R_cf_from_pf per row
    p_cf = (pk.R_cf_from_rf @ (pk.p_pf @ T[:3, :3].T + T[:3, 3])[:, :, None])[:, :, 0]
    p_cf += pk.t_cf_from_rf
    C = J[:, :, 3:] @ np.transpose(A, (0, 2, 1))  # d uv / d p_cf
    dp = np.concatenate([_skew(p_cf), np.broadcast_to(-np.eye(3), (pk.n, 3, 3))], axis=2)
    K = C @ dp  # [N, 2, 6]: d uv / d (camera's right perturbation)
    G = np.einsum("nij,nik->njk", Jw2, K)  # [N, 6, 6]: Jᵀ W K per row
    keys = [(layout[r][0], layout[r][1]) for r in rows]
    total = np.zeros((6, 6))
    for term in terms:
        S = np.zeros((6, 6))
        for n, key in enumerate(keys):
            Ad = term.moves.get(key)
            if Ad is not None:
                S += G[n] @ Ad
        M = cov @ S
        per[term.name] = M @ term.covariance @ M.T
        total += per[term.name]
    return total, per
