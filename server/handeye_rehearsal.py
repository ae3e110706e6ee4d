"""The robot-driven hand-eye rehearsed without a robot: a synthetic set shown to the simulated
cameras pose by pose, and the robot program's hand-eye commands sent through the PLC twin.

``mvpose calibrate synthetic`` renders a robot-mounted rig's board images at flange poses and
writes the poses as the robot reports them (``poses.csv``) and the truth (``truth.json``).
Here a :class:`RehearsalSet` reads such a set, :func:`show_pose` puts a pose's images in front
of the station's simulated cameras (the robot stands at that pose), and :class:`PlcHandEye`
runs HANDEYE_BEGIN / HANDEYE_ADD_POSE (the flange pose in the robot pose words) /
HANDEYE_CALCULATE on a PLC twin, answering each step's code and the hand-eye block as the PLC
reads them. ``mvpose calibrate rehearse-handeye`` (server/commands/rehearse_robot.py) and
tests/server/test_handeye_session.py use them.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from drivers.links.codecs import int_scales
from drivers.links.layout import Command, Status
from drivers.links.twin import PlcStatus, PlcTwin
from mvpose_core.calibration.files import CalibrationFile
from mvpose_core.transforms import RobotConvention, transform_error
from server.station.core import Station


@dataclass
class RehearsalSet:
    """A set of ``mvpose calibrate synthetic`` for a robot-mounted rig: the images per camera
    and pose, the poses as the robot reports them (in ``convention``), the truth."""

    root: Path
    poses: dict[str, list[float]]  # pose id -> the robot's values, in the set's convention
    truth: dict[str, Any]
    convention: RobotConvention

    @classmethod
    def load(cls, root: Path) -> RehearsalSet:
        """Read ``root``'s truth.json and poses.csv; ValueError names the file and the fault."""
        try:
            truth = json.loads((root / "truth.json").read_text())
        except (OSError, ValueError) as err:
            raise ValueError(f"{root / 'truth.json'}: {err}") from None
        if not isinstance(truth, dict) or "T_gf_from_rig" not in truth:
            raise ValueError(f"{root / 'truth.json'}: not the truth of a robot-mounted rig's set "
                             "(mvpose calibrate synthetic for a station with one)")
        conv = RobotConvention(truth["convention"])
        path = root / "poses.csv"
        try:
            with path.open(newline="") as f:
                rows = list(csv.DictReader(f))
            poses = {row["id"]: [float(row[k]) for k in conv.labels] for row in rows}
        except (OSError, KeyError, TypeError, ValueError) as err:
            raise ValueError(f"{path}: {err!r} (expected the columns id,"
                             f"{','.join(conv.labels)})") from None
        if not poses:
            raise ValueError(f"{path}: no poses")
        return cls(root, poses, truth, conv)

    @property
    def cameras(self) -> list[str]:
        return sorted(p.name for p in (self.root / "images").iterdir() if p.is_dir())

    def frames(self, sid: str) -> dict[str, np.ndarray]:
        """Each camera's image of pose ``sid`` (uint8 [H, W])."""
        out = {}
        for cam in self.cameras:
            path = self.root / "images" / cam / f"{sid}.png"
            image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                raise ValueError(f"{path}: missing or not an image")
            out[cam] = image
        return out

    def error(self, calib: CalibrationFile) -> tuple[float, float]:
        """(deg, mm) of the calibration's T_gf_from_rig against the truth."""
        rig = calib.rigs[self.truth["rig"]]
        if rig.T_gf_from_rig is None:
            raise ValueError(f"calibration {calib.id}: rig {self.truth['rig']!r} has no hand-eye")
        return transform_error(rig.T_gf_from_rig.matrix, np.array(self.truth["T_gf_from_rig"]))


def show_pose(station: Station, rset: RehearsalSet | None, sid: str | None) -> None:
    """The robot stands at pose ``sid``: the rig's simulated cameras see that pose's images
    (``rset`` None: a grey frame without the board). Blocking (reads the images)."""
    scene = station.scene
    if scene is None:
        raise ValueError(f"station {station.station.name!r}: the cameras are not simulated "
                         "(driver kind: sim)")
    if rset is None or sid is None:
        frames = {}
        for c in station.station.cameras:
            w, h = c.image_size
            frames[c.id] = np.full((h, w), 90, np.uint8)
    else:
        frames = rset.frames(sid)
    scene.set_frames(frames, view_id=station.station.views[0].id)


#: the hand-eye block's figures after a calculate, in input register order
FIGURES = ("sigma_mm", "sigma_deg", "holdout_rms_px", "holdout_mm", "holdout_deg")


class PlcHandEye:
    """The robot program's hand-eye commands through a PLC twin; each step answers the command
    result word (0 or a HandEyeCode) and the hand-eye block (poses held, the pose the answer is
    about, the stored version, the calculate's figures)."""

    def __init__(self, twin: PlcTwin, convention: RobotConvention) -> None:
        self.twin = twin
        self.scales = int_scales(convention.value)

    @staticmethod
    def answer(st: PlcStatus) -> tuple[int, dict[str, Any]]:
        done = st.has(Status.COMMAND_DONE)
        if done == st.has(Status.COMMAND_FAILED) or done != (st.command_result == 0):
            raise RuntimeError(f"the command's end is not one of COMMAND_DONE with result 0 or "
                               f"COMMAND_FAILED with a code: {st}")
        return st.command_result, {"poses": st.handeye_poses, "pose": st.handeye_pose,
                                   "version": st.handeye_version,
                                   **dict(zip(FIGURES, st.handeye_figures, strict=True))}

    async def begin(self, holdout: int) -> tuple[int, dict[str, Any]]:
        """HANDEYE_BEGIN, holding out ``holdout`` poses (0: the station's default, 3)."""
        return self.answer(await self.twin.command(Command.HANDEYE_BEGIN, holdout, timeout=30))

    async def add(self, pose: list[float] | None) -> tuple[int, dict[str, Any]]:
        """HANDEYE_ADD_POSE with ``pose`` (the recipe's convention) in the robot pose words and
        ROBOT_POSE_VALID; None: without a pose (the station refuses it)."""
        if pose is None:
            st = await self.twin.command(Command.HANDEYE_ADD_POSE, timeout=30)
        else:
            counts = [round(v * k) for v, k in zip(pose, self.scales, strict=True)]
            st = await self.twin.command_with_pose(Command.HANDEYE_ADD_POSE, counts, 60)
        return self.answer(st)

    async def calculate(self) -> tuple[int, dict[str, Any]]:
        return self.answer(await self.twin.command(Command.HANDEYE_CALCULATE, timeout=300))
