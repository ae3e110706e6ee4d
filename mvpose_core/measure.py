"""One measurement as the server pipeline calls it per trigger: pose, offsets, uncertainty, gate."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.estimate import EstimateOptions, Observation, PoseResult
from mvpose_core.gate import GateInputs, GateVerdict, evaluate_gate
from mvpose_core.offset import FrameOffset, frame_offsets
from mvpose_core.robust import Dropped, Replaced, estimate_pose_robust
from mvpose_core.scene import ViewCamera, view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.transforms import Array, RobotConvention
from mvpose_core.uncertainty import (
    calibration_covariance,
    calibration_terms,
    detector_scale,
    detector_sigmas,
    frame_adjoint,
    in_frame,
    sigma_figures,
)


@dataclass(frozen=True)
class Measurement:
    """Everything one trigger produces (all lengths mm, angles deg; frames as named)."""

    pose: PoseResult
    T_rf_from_pf: Array
    offset_rf: Array  # Δ = T_rf_from_pf · T_rf_from_pf0⁻¹ (base frame, paper eq. 6 — see offset.py)
    offset: Array  # Δ in ``convention``
    tool_offset: Array  # D = T_grasp0_from_grasp in ``convention``
    T_grasp0_from_grasp: Array  # D as a matrix
    convention: RobotConvention
    sigma_rot_deg: float  # 1σ at the grasp point: detector and calibration parts together
    sigma_trans_mm: float
    sigma_prior: tuple[float, float]  # (deg, mm) from the recipe's detector noise
    sigma_posterior: tuple[float, float] | None  # (deg, mm) scaled by the residuals; None if 0 dof
    grasp_displacement_mm: float
    rotation_deg: float
    gate: GateVerdict
    marks_used: tuple[str, ...]
    marks_missing: tuple[str, ...]
    offsets: FrameOffset
    #: the two parts of the 1σ at the grasp point (see :class:`UncertaintyParts`)
    uncertainty: UncertaintyParts | None = None
    #: observations the robust rule left out and why (mvpose_core.robust; docs/engine.md)
    dropped: tuple[Dropped, ...] = ()
    #: observations whose best candidate was replaced by a next one, and why
    replaced: tuple[Replaced, ...] = ()


@dataclass(frozen=True)
class UncertaintyParts:
    """The 1σ at the grasp point in its two parts (docs/engine.md, "Uncertainty model").

    Covariances are 6x6 over the grasp frame's right perturbation (ω [rad], v [mm]); the
    totals of :class:`Measurement` are the figures of their sum.
    """

    detector_noise_px: float  # σ of a mark centre estimated from this trigger (pooled, px)
    detector_dof: int  # 2N − 6 of the residuals it comes from
    sigma_detector_rot_deg: float
    sigma_detector_trans_mm: float
    sigma_calibration_rot_deg: float
    sigma_calibration_trans_mm: float
    covariance_detector: Array
    covariance_calibration: Array
    #: calibration term name → (deg, mm) of its share at the grasp point
    calibration_terms: dict[str, tuple[float, float]]


#: each recipe's :func:`~mvpose_core.uncertainty.frame_adjoint` of its grasp frame (recipes are
#: frozen: an entry serves that very recipe object only)
_GRASP_ADJOINTS: IdentityCache[Array] = IdentityCache(16)


def measure(
    station: StationConfig,
    recipe: RecipeConfig,
    observations: Sequence[Observation],
    flange_poses: Mapping[int, np.ndarray] | None = None,
    options: EstimateOptions = EstimateOptions(),  # noqa: B008 - frozen, immutable default
    *,
    initial_T_rf_from_pf: np.ndarray | None = None,
    cameras: Sequence[ViewCamera] | None = None,
) -> Measurement:
    """Estimate the part pose from one trigger's observations and judge it.

    ``flange_poses`` are the robot's actual flange poses per view (taught ones otherwise).
    The recipe's detector noise is the a-priori σ; its taught pose is the start of last resort.
    ``initial_T_rf_from_pf`` is a warm start tried first (e.g. the pose measured just before a
    centre correction of the same images).
    ``cameras`` are the view cameras already posed for these ``flange_poses`` (the pipeline keeps
    them per trigger); without them they are built from the station description.
    Input the estimator cannot use raises :class:`mvpose_core.estimate.PoseInputError`, whose
    ``reason`` is the gate code to report; a pose that exists but fails a tolerance comes back
    with ``gate.ok = False``.
    """
    if cameras is None:
        cameras = view_cameras(station, flange_poses)
    marks_pf = {m.id: np.asarray(m.position, dtype=float) for m in recipe.marks}
    T_rf_from_pf0 = recipe.T_rf_from_pf0.matrix
    # each centre's own σ from its mark's size and contrast (the recipe's σ for a typical one)
    observations = detector_sigmas(observations, recipe.detector_noise_px)
    robust = estimate_pose_robust(
        observations,
        cameras,
        marks_pf,
        recipe.robust,
        options,
        sigma_px=recipe.detector_noise_px,
        initial_T_rf_from_pf=T_rf_from_pf0,
        warm_start=initial_T_rf_from_pf,
    )
    pose, observations = robust.pose, robust.observations
    used = sorted({o.mark_id for o, u in zip(observations, pose.used, strict=True) if u})
    missing = tuple(m.id for m in recipe.marks if m.id not in used)
    T_pf_from_grasp = recipe.T_pf_from_grasp.matrix
    Ad = _GRASP_ADJOINTS.get((recipe,), None, lambda: frame_adjoint(T_pf_from_grasp))
    cov_grasp = in_frame(pose.covariance, Ad)
    prior = sigma_figures(cov_grasp)
    r = pose.residuals_px[pose.used]
    dof = 2 * r.shape[0] - 6
    posterior = None
    if dof > 0:
        w = np.array([1.0 / (o.sigma_px or recipe.detector_noise_px) for o in observations])[
            pose.used
        ]
        s2 = float(np.sum((r * w[:, None]) ** 2)) / dof
        posterior = sigma_figures(cov_grasp * s2)
    parts = uncertainty_parts(station, recipe, observations, cameras, marks_pf, pose, dof,
                              grasp_adjoint=Ad)
    sig_rot, sig_trans = sigma_figures(parts.covariance_detector + parts.covariance_calibration)
    off = frame_offsets(pose.T_rf_from_pf, T_rf_from_pf0, T_pf_from_grasp, recipe.robot_convention)
    lengths = np.linalg.norm(r, axis=1)
    verdict = evaluate_gate(
        GateInputs(
            marks_used=len(used),
            converged=pose.info.converged,
            termination=pose.info.termination,
            rms_px=pose.info.rms_px,
            max_residual_px=float(lengths.max()) if lengths.size else 0.0,
            sigma_rot_deg=sig_rot,
            sigma_trans_mm=sig_trans,
            offset_mm=off.grasp_displacement_mm,
            offset_deg=off.rotation_deg,
            missing=missing,
        ),
        recipe.tolerances,
        recipe.min_marks,
    )
    return Measurement(
        pose=pose,
        T_rf_from_pf=pose.T_rf_from_pf,
        offset_rf=off.T_rf_offset,
        offset=off.base,
        tool_offset=off.tool,
        T_grasp0_from_grasp=off.T_tool_offset,
        convention=off.convention,
        sigma_rot_deg=sig_rot,
        sigma_trans_mm=sig_trans,
        sigma_prior=prior,
        sigma_posterior=posterior,
        grasp_displacement_mm=off.grasp_displacement_mm,
        rotation_deg=off.rotation_deg,
        gate=verdict,
        marks_used=tuple(used),
        marks_missing=missing,
        offsets=off,
        uncertainty=parts,
        dropped=robust.dropped,
        replaced=robust.replaced,
    )


def uncertainty_parts(
    station: StationConfig,
    recipe: RecipeConfig,
    observations: Sequence[Observation],
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    pose: PoseResult,
    dof: int,
    *,
    grasp_adjoint: Array | None = None,
) -> UncertaintyParts:
    """Detector part (σ estimated from the residuals, pooled with the recipe's a-priori σ) and
    calibration part (``station.uncertainty`` propagated through the estimate's Jacobian) of
    the pose's covariance, at the recipe's grasp frame (``grasp_adjoint``: its
    :func:`~mvpose_core.uncertainty.frame_adjoint`, when the caller has it)."""
    used = [o for o, u in zip(observations, pose.used, strict=True) if u]
    sigma0 = recipe.detector_noise_px
    w = np.array([1.0 / (o.sigma_px or sigma0) for o in used])
    r = np.asarray(pose.residuals_px, dtype=float)[pose.used]
    k2 = detector_scale(float(np.sum((r * w[:, None]) ** 2)), max(dof, 0),
                        station.uncertainty.detector_prior_dof)
    Ad = (grasp_adjoint if grasp_adjoint is not None
          else frame_adjoint(recipe.T_pf_from_grasp.matrix))
    cov_det = in_frame(pose.covariance * k2, Ad)
    terms = calibration_terms(station, cameras)
    cov_cal_pf, per = calibration_covariance(
        cameras, marks_pf, [o.key for o in used], w, pose.T_rf_from_pf, terms
    )
    cov_cal = in_frame(cov_cal_pf, Ad)
    det = sigma_figures(cov_det)
    cal = sigma_figures(cov_cal)
    return UncertaintyParts(
        detector_noise_px=float(np.sqrt(k2) * sigma0),
        detector_dof=max(dof, 0),
        sigma_detector_rot_deg=det[0],
        sigma_detector_trans_mm=det[1],
        sigma_calibration_rot_deg=cal[0],
        sigma_calibration_trans_mm=cal[1],
        covariance_detector=cov_det,
        covariance_calibration=cov_cal,
        calibration_terms={
            name: sigma_figures(in_frame(c, Ad)) for name, c in per.items()
        },
    )
