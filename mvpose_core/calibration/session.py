"""A robot-driven hand-eye session: begin, add flange poses one at a time, calculate.

SICK's ``HandEye.Pose.Add / Calculate`` and Cognex's ``HEB / HE / HEE`` as data: the robot
program moves the rig in front of a fixed board, sends its actual flange pose with each add,
and asks for the result at the end. The station captures and detects (server side); this module
keeps the samples, answers each step with a :class:`HandEyeCode`, and solves on the path
``mvpose calibrate handeye`` takes (:func:`build_problem`, :func:`calibrate_handeye` with the
robot poses as measurements, :func:`handeye_report`) with the station's camera models held, as
``--base`` holds them. Some poses are held out of the solve; their reprojection RMS and the
distance between the recorded flange pose and the one the images imply are the hold-out check.
No I/O: the images and the calibration version are the server's.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.calibration.codes import HandEyeCode
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.files import (
    CalibrationFile,
    CameraCalibration,
    InputsSummary,
    RigCalibration,
    make_calibration,
    merge,
    pose,
)
from mvpose_core.calibration.handeye import (
    HandEyeOptions,
    HandEyeResult,
    build_problem,
    calibrate_handeye,
)
from mvpose_core.calibration.intrinsics import board_pose
from mvpose_core.calibration.report import CalibrationReport, handeye_report
from mvpose_core.calibration.robotposes import check_motion, check_units
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import (
    Array,
    RobotConvention,
    apply,
    compose,
    from_robot,
    invert,
    transform_error,
)

#: the most poses one session keeps
MAX_POSES = 200
# degrees-convention rotation values all within this of zero: radians where degrees belong
_RADIAN_LIKE = np.pi + 0.01


__all__ = ["HandEyeCode", "HandEyeSession", "HoldOut", "Sample", "SessionError",
           "SessionResult", "holdout_text"]


class SessionError(ValueError):
    """A step refused, with its code; the message names the pose and the problem."""

    def __init__(self, code: HandEyeCode, message: str) -> None:
        super().__init__(message)
        self.code = code


@dataclass(frozen=True)
class Sample:
    """One added pose: the robot's flange pose as sent and as a transform, and the board seen
    by each camera of the rig (None where a camera did not find it)."""

    sid: str
    values: tuple[float, ...]  # in the session's robot convention
    T_rf_from_gf: Array
    detections: dict[str, Detection | None]


@dataclass(frozen=True)
class HoldOut:
    """A held-out pose checked against the result: the board's reprojection RMS (px) in the
    cameras that saw it, and how far the recorded flange pose is from the one the reference
    camera's image implies (mm, deg)."""

    rms_px: float
    mm: float
    deg: float


@dataclass(frozen=True)
class SessionResult:
    """A calculated session: the solve, its report, the hold-out check and the file."""

    result: HandEyeResult
    report: CalibrationReport
    holdout: dict[str, HoldOut]
    calibration: CalibrationFile

    @property
    def holdout_rms_px(self) -> float:
        return float(np.sqrt(np.mean([h.rms_px ** 2 for h in self.holdout.values()]))) \
            if self.holdout else 0.0

    @property
    def holdout_mm(self) -> float:
        return max((h.mm for h in self.holdout.values()), default=0.0)

    @property
    def holdout_deg(self) -> float:
        return max((h.deg for h in self.holdout.values()), default=0.0)

    def summary(self) -> dict[str, Any]:
        r = self.result
        return {
            "sigma_mm": float(r.sigma_mm), "sigma_deg": float(r.sigma_deg),
            "rms_px": float(r.rms_px), "samples_used": sorted(r.per_sample_rms_px),
            "left_out": dict(r.left_out), "warnings": list(self.report.warnings),
            "holdout": {sid: {"rms_px": h.rms_px, "mm": h.mm, "deg": h.deg}
                        for sid, h in self.holdout.items()},
            "holdout_rms_px": self.holdout_rms_px, "holdout_max_mm": self.holdout_mm,
            "holdout_max_deg": self.holdout_deg,
        }


@dataclass
class HandEyeSession:
    """The samples of one robot-mounted rig's hand-eye, added in the robot's own convention.

    ``cameras`` are the rig's camera models (first: the reference CF0) and ``T_cfc_from_cf0``
    their relations, both held in the solve; ``T_rig_from_cf0`` is the rig's nominal pose of
    the reference camera (the rig frame keeps the station file's meaning). Every ``holdout``-th
    pose, spread over the session, is kept out of the solve and checked against it.
    """

    station: str
    rig: str
    board: BoardSpec
    convention: RobotConvention
    cameras: dict[str, CameraModel]
    T_cfc_from_cf0: dict[str, Array]
    T_rig_from_cf0: Array
    holdout: int = 3
    options: HandEyeOptions = HandEyeOptions(refine_intrinsics=False)
    samples: dict[str, Sample] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.holdout < 0:
            raise ValueError(f"holdout must be ≥ 0, got {self.holdout}")

    @property
    def needed(self) -> int:
        """Poses a calculate needs: the solve's minimum plus the hold-out."""
        return self.options.min_samples + self.holdout

    def next_id(self) -> str:
        return f"{len(self.samples) + 1:03d}"

    # ------------------------------------------------------------------ add
    def pose_of(self, values: Sequence[float] | None, sid: str) -> Array:
        """The flange pose ``values`` (the session's convention) as ``T_rf_from_gf``; refused
        (BAD_POSE, UNIT_SUSPICIOUS) with a message naming pose ``sid``."""
        conv = self.convention
        if values is None:
            raise SessionError(HandEyeCode.BAD_POSE,
                               f"hand-eye pose {sid}: no robot pose came with it")
        v = [float(x) for x in values]
        if len(v) != conv.size or not all(np.isfinite(v)):
            raise SessionError(HandEyeCode.BAD_POSE, (
                f"hand-eye pose {sid}: a {conv.value} pose has {conv.size} finite values "
                f"{list(conv.labels)}, got {v}"))
        try:
            T = from_robot(v, conv)
        except ValueError as err:
            raise SessionError(HandEyeCode.BAD_POSE, f"hand-eye pose {sid}: {err}") from None
        if conv is RobotConvention.UR and float(np.linalg.norm(v[3:6])) > 2 * np.pi + 0.01:
            raise SessionError(HandEyeCode.UNIT_SUSPICIOUS, (
                f"hand-eye pose {sid}: rotation vector {v[3:6]} is longer than 2π: degrees "
                "where the ur convention wants radians?"))
        try:
            check_units({sid: T}, conv, f"hand-eye pose {sid}")
        except CalibrationError as err:
            raise SessionError(HandEyeCode.UNIT_SUSPICIOUS, str(err)) from None
        return T

    def add(self, values: Sequence[float] | None, detections: Mapping[str, Detection | None],
            sid: str | None = None) -> Sample:
        """Keep a pose with the board as each camera saw it; refused when it is not a pose or
        no camera found the board (the pose is then not kept)."""
        sid = sid or self.next_id()
        if len(self.samples) >= MAX_POSES:
            raise SessionError(HandEyeCode.SESSION_FULL,
                               f"hand-eye pose {sid}: the session holds {MAX_POSES} poses already")
        if sid in self.samples:
            raise SessionError(HandEyeCode.BAD_POSE, f"hand-eye pose {sid}: added already")
        T = self.pose_of(values, sid)
        assert values is not None  # pose_of refuses a missing pose
        unknown = sorted(set(detections) - set(self.cameras))
        if unknown:
            raise ValueError(f"hand-eye pose {sid}: detections of cameras {unknown} not in rig "
                             f"{self.rig!r}")
        dets = {c: detections.get(c) for c in self.cameras}
        if all(d is None for d in dets.values()):
            raise SessionError(HandEyeCode.BOARD_NOT_FOUND, (
                f"hand-eye pose {sid}: board {self.board} not found by any camera of rig "
                f"{self.rig!r} ({', '.join(self.cameras)}); move the robot so the board is in "
                "view and add the pose again"))
        sample = Sample(sid, tuple(float(x) for x in values), T, dets)
        self.samples[sid] = sample
        return sample

    # ------------------------------------------------------------------ calculate
    def held_out(self) -> list[str]:
        """The held-out pose ids: ``holdout`` of them spread evenly over the session."""
        ids = list(self.samples)
        n, h = len(ids), min(self.holdout, max(0, len(ids) - self.options.min_samples))
        return [ids[int((k + 0.5) * n / h)] for k in range(h)] if h else []

    def calculate(self, created_by: str = "", base: CalibrationFile | None = None,
                  images: str = "") -> SessionResult:
        """Solve on every pose but the held-out ones, check those, and build the calibration
        file (on top of ``base``, the station's calibration). Refusals raise SessionError."""
        n = len(self.samples)
        if n < self.needed:
            raise SessionError(HandEyeCode.TOO_FEW_POSES, (
                f"hand-eye: {n} poses with the board found, need at least {self.needed} "
                f"({self.options.min_samples} to solve, {self.holdout} held out to check it)"))
        self._check_angle_unit()
        held = self.held_out()
        used = [sid for sid in self.samples if sid not in held]
        poses = {sid: self.samples[sid].T_rf_from_gf for sid in used}
        dets = {c: {sid: self.samples[sid].detections[c] for sid in used} for c in self.cameras}
        try:
            problem, rejected = build_problem("robot", self.board, self.cameras, poses, dets,
                                              self.T_cfc_from_cf0)
            self._check_motion(problem.robot_poses, problem.detections)
            res = calibrate_handeye(problem, self.options, rejected=rejected)
        except CalibrationError as err:
            raise SessionError(_code_of(str(err)), str(err)) from None
        report = handeye_report(problem, res)
        holdout = {sid: self._check(res, self.samples[sid]) for sid in held}
        calib = self._calibration(res, report, holdout, base, images)
        return SessionResult(res, report, holdout, calib)

    def _check_angle_unit(self) -> None:
        if self.convention in (RobotConvention.UR, RobotConvention.ABB):
            return  # radians and unit quaternions: the add checked them
        angles = np.array([s.values[3:6] for s in self.samples.values()], dtype=float)
        if angles.size and float(np.max(np.abs(angles))) <= _RADIAN_LIKE:
            raise SessionError(HandEyeCode.UNIT_SUSPICIOUS, (
                f"hand-eye: every rotation value of the {len(angles)} poses is within ±π: "
                f"radians where the {self.convention.value} convention wants degrees?"))

    def _check_motion(self, poses: Mapping[str, Array],
                      dets: Mapping[str, Mapping[str, Detection]]) -> None:
        ref = next(iter(self.cameras))
        ids = [sid for sid in poses if ref in dets[sid]]
        B = {sid: board_pose(self.cameras[ref], dets[sid][ref], self.board) for sid in ids}
        check_motion({sid: poses[sid] for sid in ids}, B, "hand-eye")

    def _check(self, res: HandEyeResult, sample: Sample) -> HoldOut:
        """The result against a pose it did not see."""
        A = sample.T_rf_from_gf
        sq: list[Array] = []
        implied: Array | None = None
        for cid, det in sample.detections.items():
            if det is None:
                continue
            cam = res.cameras[cid]
            T_cf_from_bf = compose(res.T_cfc_from_cf0[cid], invert(res.X), invert(A), res.Y)
            uv = cam.project(apply(T_cf_from_bf, self.board.object_points[det.ids]))
            sq.append(np.sum((uv - det.uv) ** 2, axis=1))
            if implied is None:  # T_rf_from_gf as this camera's view of the board implies it
                B = board_pose(cam, det, self.board)
                T_cf0_from_bf = compose(invert(res.T_cfc_from_cf0[cid]), B)
                implied = compose(res.Y, invert(T_cf0_from_bf), invert(res.X))
        assert implied is not None  # add() keeps only poses some camera found the board in
        deg, mm = transform_error(implied, A)
        return HoldOut(float(np.sqrt(np.mean(np.concatenate(sq)))), mm, deg)

    def _calibration(self, res: HandEyeResult, report: CalibrationReport,
                     holdout: Mapping[str, HoldOut], base: CalibrationFile | None,
                     images: str) -> CalibrationFile:
        """The calibration file as ``mvpose calibrate handeye --base`` writes it."""
        cams = list(self.cameras)
        Trig = self.T_rig_from_cf0
        rig = RigCalibration(
            T_gf_from_rig=pose(res.X @ invert(Trig)),
            T_rig_from_cf={c: pose(Trig @ invert(res.T_cfc_from_cf0[c])) for c in cams},
        )
        cameras, rigs = merge(base, {c: CameraCalibration.from_model(res.cameras[c])
                                     for c in cams}, {self.rig: rig})
        rejected = dict(report.rejected)
        rejected.update({sid: "held out: checks the result" for sid in holdout})
        inputs = InputsSummary(
            board=str(self.board), images=images, robot_poses="robot-driven session",
            robot_convention=self.convention.value,
            samples_used=sorted(res.per_sample_rms_px), samples_rejected=rejected,
            based_on=base.ref if base is not None else None,
        )
        reports: dict[str, Any] = {report.kind: report.to_dict(), "hold-out": {
            sid: {"rms_px": h.rms_px, "mm": h.mm, "deg": h.deg} for sid, h in holdout.items()}}
        return make_calibration("handeye", inputs, cameras, rigs, reports, station=self.station)

    def poses_csv(self) -> str:
        """The added poses as a robot-pose file of the session's convention (id first)."""
        rows = [",".join(["id", *self.convention.labels])]
        rows += [s.sid + "," + ",".join(repr(v) for v in s.values)
                 for s in self.samples.values()]
        return "\n".join(rows) + "\n"


def holdout_text(holdout: Mapping[str, HoldOut]) -> str:
    """The hold-out check as the report's last lines."""
    if not holdout:
        return "hold-out: none (every pose was used)"
    lines = [f"hold-out: {len(holdout)} poses kept out of the solve"]
    lines += [f"  pose {sid}: reprojection RMS {h.rms_px:.3f} px, recorded flange pose "
              f"{h.mm:.3f} mm / {h.deg:.4f}° from the one its image implies"
              for sid, h in holdout.items()]
    return "\n".join(lines)


def _code_of(message: str) -> HandEyeCode:
    """The code of a refusal from the solver path (its one exception type carries text)."""
    m = message.lower()
    if "pure translations" in m or "about one axis" in m:
        return HandEyeCode.TOO_LITTLE_ROTATION
    if "wrong unit" in m or "as far as the camera sees" in m:
        return HandEyeCode.UNIT_SUSPICIOUS
    if "declared size" in m:
        return HandEyeCode.BOARD_SCALE
    if "outliers" in m:
        return HandEyeCode.OUTLIERS
    if "too few" in m:
        return HandEyeCode.TOO_FEW_POSES
    if "do not fit" in m or "no solver gave a plausible" in m:
        return HandEyeCode.POSES_DO_NOT_FIT
    return HandEyeCode.FAILED
