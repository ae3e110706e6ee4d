"""One measurement as the server pipeline calls it per trigger: pose, offsets, uncertainty, gate."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from mvpose_core.estimate import EstimateOptions, Observation, PoseResult
from mvpose_core.gate import GateInputs, GateVerdict, evaluate_gate
from mvpose_core.offset import FrameOffset, frame_offsets
from mvpose_core.robust import Dropped, Replaced, estimate_pose_robust
from mvpose_core.scene import ViewCamera, view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.transforms import Array, RobotConvention
from mvpose_core.uncertainty import covariance_in_frame, sigma_figures


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
    sigma_rot_deg: float  # 1σ at the grasp point: max(a priori, a posteriori)
    sigma_trans_mm: float
    sigma_prior: tuple[float, float]  # (deg, mm) from the recipe's detector noise
    sigma_posterior: tuple[float, float] | None  # (deg, mm) scaled by the residuals; None if 0 dof
    grasp_displacement_mm: float
    rotation_deg: float
    gate: GateVerdict
    marks_used: tuple[str, ...]
    marks_missing: tuple[str, ...]
    offsets: FrameOffset
    #: observations the robust rule left out and why (mvpose_core.robust; docs/engine.md)
    dropped: tuple[Dropped, ...] = ()
    #: observations whose best candidate was replaced by a next one, and why
    replaced: tuple[Replaced, ...] = ()


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
    cov_grasp = covariance_in_frame(pose.covariance, T_pf_from_grasp)
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
    sig_rot = max(prior[0], posterior[0]) if posterior else prior[0]
    sig_trans = max(prior[1], posterior[1]) if posterior else prior[1]
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
        dropped=robust.dropped,
        replaced=robust.replaced,
    )
