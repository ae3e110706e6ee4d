"""Fixed station cameras: camera-to-camera relations from images alone, then one rigid placement
of the whole station in the robot frame, so robot inaccuracy cannot bend the station.

Step 1 (:func:`relate_cameras`): a bundle adjustment over every board placement seen by two or
more cameras at once gives ``T_ref_from_cf`` for each camera of a connected group.
Step 2 (:func:`place_group`): board placements whose pose in RF is known (corners touched with a
pointer, or the board carried by the robot: ``T_rf_from_gf · T_gf_from_bf``) give one rigid
``T_rf_from_ref`` per group, fitted over all corners of all placements.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.handeye import mean_transform
from mvpose_core.calibration.intrinsics import board_pose, split_detections
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, apply, compose, invert, make_transform, rotvec_to_matrix


@dataclass(frozen=True)
class CameraGroup:
    """Cameras related to each other through shared board placements."""

    reference: str
    T_ref_from_cf: dict[str, Array]
    T_ref_from_bf: dict[str, Array]  # every placement seen by the group
    residuals: dict[str, Array]  # sample → ["N", 2] px over the group's cameras


@dataclass(frozen=True)
class StationResult:
    """Pose of every fixed camera in RF, with the quality of both steps."""

    T_rf_from_cf: dict[str, Array]
    groups: list[CameraGroup]
    placement_rms_mm: dict[str, float]  # per group reference: RF measurements vs rigid station
    per_sample_rms_px: dict[str, float]
    rejected: dict[str, str] = field(default_factory=dict)


def _perturb(T0: Array, p: Array) -> Array:
    return make_transform(rotvec_to_matrix(p[:3]) @ T0[:3, :3], T0[:3, 3] + p[3:])


def relate_cameras(
    board: BoardSpec,
    cameras: Mapping[str, CameraModel],
    detections: Mapping[str, Mapping[str, Detection]],
    reference: str,
) -> CameraGroup:
    """Bundle adjustment of one connected group; ``detections`` is camera → sample → found board."""
    B = {
        (cid, sid): board_pose(cameras[cid], d, board)
        for cid, per in detections.items()
        for sid, d in per.items()
    }
    # Chain cameras outwards from the reference through shared samples (breadth first).
    T_ref_from_cf = {reference: np.eye(4)}
    frontier = [reference]
    while frontier:
        known = frontier.pop(0)
        for cid in detections:
            if cid in T_ref_from_cf:
                continue
            shared = sorted(set(detections[known]) & set(detections[cid]))
            if shared:
                links = [
                    compose(T_ref_from_cf[known], B[(known, s)], invert(B[(cid, s)]))
                    for s in shared
                ]
                T_ref_from_cf[cid] = mean_transform(links)
                frontier.append(cid)
    cams = [c for c in detections if c in T_ref_from_cf]
    samples = sorted({s for c in cams for s in detections[c]})
    T_ref_from_bf = {
        s: mean_transform(
            [compose(T_ref_from_cf[c], B[(c, s)]) for c in cams if s in detections[c]]
        )
        for s in samples
    }
    movable = [c for c in cams if c != reference]
    obs = [(c, s, detections[c][s]) for c in cams for s in samples if s in detections[c]]
    pts = [d.object_points(board) for _, _, d in obs]
    col = {("cam", c): 6 * k for k, c in enumerate(movable)}
    col.update({("bf", s): 6 * (len(movable) + k) for k, s in enumerate(samples)})
    n_par = 6 * (len(movable) + len(samples))

    def poses(p: Array) -> tuple[dict[str, Array], dict[str, Array]]:
        tc = {
            c: _perturb(T_ref_from_cf[c], p[col[("cam", c)] : col[("cam", c)] + 6]) for c in movable
        }
        tc[reference] = np.eye(4)
        tb = {
            s: _perturb(T_ref_from_bf[s], p[col[("bf", s)] : col[("bf", s)] + 6]) for s in samples
        }
        return tc, tb

    def fun(p: Array) -> Array:
        tc, tb = poses(p)
        return np.concatenate(
            [
                (cameras[c].project(apply(compose(invert(tc[c]), tb[s]), P)) - d.uv).ravel()
                for (c, s, d), P in zip(obs, pts, strict=True)
            ]
        )

    # Each residual block depends on its camera's and its placement's 6 parameters only.
    sparsity = lil_matrix((sum(2 * len(d) for _, _, d in obs), n_par), dtype=int)
    row = 0
    for c, s, d in obs:
        n = 2 * len(d)
        if c != reference:
            sparsity[row : row + n, col[("cam", c)] : col[("cam", c)] + 6] = 1
        sparsity[row : row + n, col[("bf", s)] : col[("bf", s)] + 6] = 1
        row += n
    sol = least_squares(fun, np.zeros(n_par), jac_sparsity=sparsity, method="trf", x_scale="jac")
    tc, tb = poses(sol.x)
    res: dict[str, list[Array]] = {}
    k = 0
    for _, s, d in obs:
        n = 2 * len(d)
        res.setdefault(s, []).append(sol.fun[k : k + n].reshape(-1, 2))
        k += n
    return CameraGroup(
        reference=reference,
        T_ref_from_cf={c: tc[c] for c in cams},
        T_ref_from_bf=tb,
        residuals={s: np.concatenate(r) for s, r in res.items()},
    )


def place_group(
    board: BoardSpec, group: CameraGroup, T_rf_from_bf: Mapping[str, Array]
) -> tuple[Array, float]:
    """One rigid ``T_rf_from_ref`` from every corner of every placement known in both frames,
    and the RMS distance (mm) between the two after the fit."""
    common = sorted(set(group.T_ref_from_bf) & set(T_rf_from_bf))
    if not common:
        raise CalibrationError(
            f"station: no board placement seen by camera group {sorted(group.T_ref_from_cf)} "
            "has a pose in the robot frame"
        )
    P = board.object_points
    p_ref = np.concatenate([apply(group.T_ref_from_bf[s], P) for s in common])
    p_rf = np.concatenate([apply(T_rf_from_bf[s], P) for s in common])
    c_ref, c_rf = p_ref.mean(0), p_rf.mean(0)
    rot, _ = Rotation.align_vectors(p_rf - c_rf, p_ref - c_ref)
    T = make_transform(rot.as_matrix(), c_rf - rot.apply(c_ref))
    rms = float(np.sqrt(np.mean(np.sum((apply(T, p_ref) - p_rf) ** 2, axis=1))))
    return T, rms


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
) -> StationResult:
    """Relate the cameras from images, then place each connected group rigidly in RF.

    ``detections`` is camera → sample → detection (None: board not seen by that camera).
    Cameras that never share a placement with the others form their own group, placed on
    its own (reported in :attr:`StationResult.groups`).
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
        g = relate_cameras(board, cameras, {c: found[c] for c in remaining}, remaining[0])
        groups.append(g)
        remaining = [c for c in remaining if c not in g.T_ref_from_cf]
    T_rf_from_cf: dict[str, Array] = {}
    placement: dict[str, float] = {}
    for g in groups:
        T, rms = place_group(board, g, T_rf_from_bf)
        placement[g.reference] = rms
        for c, Tc in g.T_ref_from_cf.items():
            T_rf_from_cf[c] = compose(T, Tc)
    residuals: dict[str, list[Array]] = {}
    for g in groups:
        for s, r in g.residuals.items():
            residuals.setdefault(s, []).append(r)
    per_sample = {
        s: float(np.sqrt(np.mean(np.sum(np.concatenate(r) ** 2, axis=1))))
        for s, r in sorted(residuals.items())
    }
    rejected = {s: "; ".join(n) for s, n in notes.items() if s not in per_sample}
    return StationResult(T_rf_from_cf, groups, placement, per_sample, rejected)
