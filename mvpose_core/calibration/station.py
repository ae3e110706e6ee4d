"""Fixed station cameras: camera-to-camera relations from images alone, then one rigid placement
of the whole station in the robot frame, so robot inaccuracy cannot bend the station.

Step 1 (:func:`~mvpose_core.calibration.group.adjust_group`): an images-only bundle adjustment
over every board placement (the intrinsics adjusted with the poses) gives ``T_ref_from_cf`` for
each camera of a connected group, with its covariance.
Step 2 (:func:`place_group`): board placements whose pose in RF is known (corners touched with a
pointer, or the board carried by the robot: ``T_rf_from_gf · T_gf_from_bf``) give one rigid
``T_rf_from_ref`` per group, fitted over all corners of all placements; its 1σ is the jackknife
over the placements (their RF errors are rigid per placement, so the corners are not independent).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.group import CameraGroup, adjust_group
from mvpose_core.calibration.intrinsics import split_detections
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, apply, compose, make_transform, matrix_to_rotvec

__all__ = ["CameraGroup", "StationResult", "calibrate_station", "place_group"]


@dataclass(frozen=True)
class StationResult:
    """Pose of every fixed camera in RF, with the quality of both steps."""

    T_rf_from_cf: dict[str, Array]
    groups: list[CameraGroup]
    placement_rms_mm: dict[str, float]  # per group reference: RF measurements vs rigid station
    per_sample_rms_px: dict[str, float]
    rejected: dict[str, str] = field(default_factory=dict)
    cameras: dict[str, CameraModel] = field(default_factory=dict)  # intrinsics after step 1
    #: per camera 1σ (mm, deg) of its pose relative to its group's reference camera (step 1)
    sigma_relative: dict[str, tuple[float, float]] = field(default_factory=dict)
    #: per camera 1σ (mm, deg) of its pose in RF: the group's placement (jackknife over the
    #: placements) and the relative part, root-sum-squared
    sigma_rf: dict[str, tuple[float, float]] = field(default_factory=dict)


def _rigid(p_ref: Array, p_rf: Array) -> Array:
    c_ref, c_rf = p_ref.mean(0), p_rf.mean(0)
    rot, _ = Rotation.align_vectors(p_rf - c_rf, p_ref - c_ref)
    return make_transform(rot.as_matrix(), c_rf - rot.apply(c_ref))


def place_group(
    board: BoardSpec, group: CameraGroup, T_rf_from_bf: Mapping[str, Array]
) -> tuple[Array, float]:
    """One rigid ``T_rf_from_ref`` from every corner of every placement known in both frames,
    and the RMS distance (mm) between the two after the fit."""
    common = _common(group, T_rf_from_bf)
    P = board.object_points
    p_ref = np.concatenate([apply(group.T_ref_from_bf[s], P) for s in common])
    p_rf = np.concatenate([apply(T_rf_from_bf[s], P) for s in common])
    T = _rigid(p_ref, p_rf)
    rms = float(np.sqrt(np.mean(np.sum((apply(T, p_ref) - p_rf) ** 2, axis=1))))
    return T, rms


def _common(group: CameraGroup, T_rf_from_bf: Mapping[str, Array]) -> list[str]:
    common = sorted(set(group.T_ref_from_bf) & set(T_rf_from_bf))
    if not common:
        raise CalibrationError(
            f"station: no board placement seen by camera group {sorted(group.T_ref_from_cf)} "
            "has a pose in the robot frame"
        )
    return common


def placement_sigma(
    board: BoardSpec, group: CameraGroup, T_rf_from_bf: Mapping[str, Array]
) -> dict[str, tuple[float, float]]:
    """Per camera of the group, the jackknife 1σ (mm, deg; RSS over the axes) of its pose in
    RF due to the group's placement: the fit repeated without each placement in turn. NaN with
    fewer than three placements."""
    common = _common(group, T_rf_from_bf)
    n = len(common)
    if n < 3:
        return {c: (float("nan"), float("nan")) for c in group.T_ref_from_cf}
    P = board.object_points
    p_ref = {s: apply(group.T_ref_from_bf[s], P) for s in common}
    p_rf = {s: apply(T_rf_from_bf[s], P) for s in common}
    T = _rigid(np.concatenate(list(p_ref.values())), np.concatenate(list(p_rf.values())))
    runs = [
        _rigid(
            np.concatenate([p_ref[s] for s in common if s != out]),
            np.concatenate([p_rf[s] for s in common if s != out]),
        )
        for out in common
    ]
    sig: dict[str, tuple[float, float]] = {}
    for c, Tc in group.T_ref_from_cf.items():
        full = T @ Tc
        d = np.array(
            [
                np.r_[
                    (Ti @ Tc)[:3, 3] - full[:3, 3],
                    matrix_to_rotvec((Ti @ Tc)[:3, :3] @ full[:3, :3].T),
                ]
                for Ti in runs
            ]
        )
        var = (n - 1) / n * np.sum((d - d.mean(0)) ** 2, axis=0)
        sig[c] = float(np.sqrt(var[:3].sum())), float(np.degrees(np.sqrt(var[3:].sum())))
    return sig


def board_poses_from_robot(
    robot_poses: Mapping[str, Array], T_gf_from_bf: Array
) -> dict[str, Array]:
    """``T_rf_from_bf`` of a board carried by the robot at each sample."""
    return {sid: compose(A, T_gf_from_bf) for sid, A in robot_poses.items()}


def calibrate_station(
    board: BoardSpec,
    cameras: Mapping[str, CameraModel],
    detections: Mapping[str, Mapping[str, Detection | None]],
    T_rf_from_bf: Mapping[str, Array],
    min_corners: int = 6,
    refine_intrinsics: bool = True,
) -> StationResult:
    """Relate the cameras from images, then place each connected group rigidly in RF.

    ``detections`` is camera → sample → detection (None: board not seen by that camera).
    Cameras that never share a placement with the others form their own group, placed on
    its own (reported in :attr:`StationResult.groups`). With ``refine_intrinsics`` the cameras'
    intrinsics are adjusted with the relations (the shared placements fix them better than each
    camera's own images; held, their errors bend the station by several times the images-only
    result).
    """
    found: dict[str, dict[str, Detection]] = {}
    notes: dict[str, list[str]] = {}
    for cid in cameras:
        if cid not in detections:
            raise CalibrationError(f"station: no images for camera {cid!r}")
        used, rej = split_detections(detections[cid], min_corners, f"station camera {cid!r}")
        found[cid] = used
        for sid, why in rej.items():
            notes.setdefault(sid, []).append(f"{cid}: {why}")
    remaining = list(cameras)
    groups: list[CameraGroup] = []
    while remaining:
        g = adjust_group(
            board, cameras, {c: found[c] for c in remaining}, remaining[0], refine_intrinsics
        )
        groups.append(g)
        remaining = [c for c in remaining if c not in g.T_ref_from_cf]
    T_rf_from_cf: dict[str, Array] = {}
    placement: dict[str, float] = {}
    sigma_rel: dict[str, tuple[float, float]] = {}
    sigma_rf: dict[str, tuple[float, float]] = {}
    for g in groups:
        T, rms = place_group(board, g, T_rf_from_bf)
        placement[g.reference] = rms
        jack = placement_sigma(board, g, T_rf_from_bf)
        for c, Tc in g.T_ref_from_cf.items():
            T_rf_from_cf[c] = compose(T, Tc)
            sigma_rel[c] = g.sigma(c)
            sigma_rf[c] = (
                float(np.hypot(jack[c][0], sigma_rel[c][0])),
                float(np.hypot(jack[c][1], sigma_rel[c][1])),
            )
    residuals: dict[str, list[Array]] = {}
    for g in groups:
        for s, r in g.residuals.items():
            residuals.setdefault(s, []).append(r)
    per_sample = {
        s: float(np.sqrt(np.mean(np.sum(np.concatenate(r) ** 2, axis=1))))
        for s, r in sorted(residuals.items())
    }
    rejected = {s: "; ".join(n) for s, n in notes.items() if s not in per_sample}
    models = {c: m for g in groups for c, m in g.cameras.items()}
    return StationResult(
        T_rf_from_cf, groups, placement, per_sample, rejected, models, sigma_rel, sigma_rf
    )
