"""Camera intrinsics from board images (Zhang's method, solved by OpenCV), keyed by sample id."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, invert, make_transform, rotvec_to_matrix

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True)
class IntrinsicsOptions:
    """How many distortion terms to estimate and how many samples to require."""

    n_distortion: int = 5  # 4 (k1 k2 p1 p2), 5 (+k3) or 8 (rational model)
    fix_aspect_ratio: bool = False
    min_samples: int = 6
    min_corners: int = 6


@dataclass(frozen=True)
class IntrinsicsResult:
    """A calibrated camera and how well every sample fits it."""

    camera_id: str
    camera: CameraModel
    rms_px: float
    per_sample_rms_px: dict[str, float]
    T_cf_from_bf: dict[str, Array]  # board pose per used sample
    std: dict[str, float]  # 1σ of fx fy cx cy k1 ... from OpenCV
    rejected: dict[str, str] = field(default_factory=dict)  # sample id → reason

    @property
    def used(self) -> list[str]:
        return list(self.per_sample_rms_px)


def split_detections(
    detections: Mapping[str, Detection | None], min_corners: int, what: str
) -> tuple[dict[str, Detection], dict[str, str]]:
    """Usable detections by id, and the left-out ids with the reason (never shifted)."""
    used: dict[str, Detection] = {}
    rejected: dict[str, str] = {}
    for sid in sorted(detections):
        d = detections[sid]
        if d is None:
            rejected[sid] = "board not found"
        elif len(d) < min_corners:
            rejected[sid] = f"only {len(d)} corners (need {min_corners})"
        else:
            used[sid] = d
    if detections and not used:
        raise CalibrationError(
            f"{what}: the board was not found in any of the {len(detections)} images "
            f"({', '.join(sorted(detections)[:5])}{', ...' if len(detections) > 5 else ''})"
        )
    return used, rejected


def require_samples(n: int, minimum: int, what: str, ids: list[str]) -> None:
    if n < minimum:
        raise CalibrationError(
            f"{what}: too few usable samples: {n} ({', '.join(ids) or 'none'}), "
            f"need at least {minimum}"
        )


def _flags(opt: IntrinsicsOptions) -> int:
    flags = 0
    if opt.n_distortion == 4:
        flags |= cv2.CALIB_FIX_K3
    elif opt.n_distortion == 8:
        flags |= cv2.CALIB_RATIONAL_MODEL
    elif opt.n_distortion != 5:
        raise ValueError(f"n_distortion must be 4, 5 or 8, got {opt.n_distortion}")
    if opt.fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    return flags


def calibrate_intrinsics(
    camera_id: str,
    detections: Mapping[str, Detection | None],
    board: BoardSpec,
    image_size: tuple[int, int],
    options: IntrinsicsOptions = IntrinsicsOptions(),
) -> IntrinsicsResult:
    """Calibrate one camera from board detections keyed by sample id (None = board not found)."""
    what = f"intrinsics of camera {camera_id!r}"
    used, rejected = split_detections(detections, options.min_corners, what)
    require_samples(len(used), options.min_samples, what, list(used))
    ids = list(used)
    obj = [used[i].object_points(board).astype(np.float32) for i in ids]
    img = [used[i].uv.astype(np.float32).reshape(-1, 1, 2) for i in ids]
    w, h = image_size
    K0 = None
    flags = _flags(options)
    if board.kind == "charuco" or options.fix_aspect_ratio:
        # Partial views and fixed aspect need a start; OpenCV's own planar initialisation.
        K0 = cv2.initCameraMatrix2D(obj, img, (w, h))
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    rms, K, dist, rvecs, tvecs, std_in, _, per_view = cv2.calibrateCameraExtended(  # type: ignore[call-overload]
        obj, img, (w, h), K0, None, flags=flags, criteria=_CRITERIA
    )
    n = {4: 4, 5: 5, 8: 8}[options.n_distortion]
    d = tuple(float(x) for x in dist.reshape(-1)[:n])
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{what}: OpenCV returned an invalid camera matrix {K.tolist()}")
    cam = CameraModel(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), w, h, d)
    names = ["fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"]
    std = {nm: float(v) for nm, v in zip(names[: 4 + n], std_in.reshape(-1)[: 4 + n], strict=True)}
    poses = {
        i: make_transform(rotvec_to_matrix(r.reshape(3)), t.reshape(3))
        for i, r, t in zip(ids, rvecs, tvecs, strict=True)
    }
    return IntrinsicsResult(
        camera_id=camera_id,
        camera=cam,
        rms_px=float(rms),
        per_sample_rms_px={i: float(e) for i, e in zip(ids, per_view.reshape(-1), strict=True)},
        T_cf_from_bf=poses,
        std=std,
        rejected=rejected,
    )


def board_pose(camera: CameraModel, detection: Detection, board: BoardSpec) -> Array:
    """``T_cf_from_bf`` of one detection with known intrinsics (OpenCV PnP, LM-refined)."""
    obj = detection.object_points(board)
    ok, rvec, tvec = cv2.solvePnP(
        obj, detection.uv, camera.K, camera.dist_array, flags=cv2.SOLVEPNP_IPPE
    )
    if not ok:
        raise CalibrationError(f"board pose: PnP failed for {len(detection)} corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, detection.uv, camera.K, camera.dist_array, rvec, tvec)
    return make_transform(rotvec_to_matrix(rvec.reshape(3)), tvec.reshape(3))


def camera_positions_in_board(poses: Mapping[str, Array]) -> Array:
    """Camera centres in BF, ``["N", 3]``: used to check that the views are spread out."""
    return np.array([invert(T)[:3, 3] for T in poses.values()])
