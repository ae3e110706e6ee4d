"""The robot-driven hand-eye on the station: begin, add pose, calculate, from any link.

A session (:class:`mvpose_core.calibration.session.HandEyeSession`) looks at the station file's
``calibration_board`` with the cameras of its first robot-mounted rig, under the calibration the
station measures with (intrinsics and the rig's camera relations held, as ``mvpose calibrate
handeye --base`` holds them). Each add grabs every camera of the rig on the trigger thread,
between triggers, at the first view holding the rig; the board is detected off that thread and
the images are kept in ``<data_dir>/handeye/<session>/<camera>/<pose>.png`` beside the session's
``poses.csv``. A calculate solves off the station loop, writes ``report.txt`` and
``residuals.png`` there, and stores the calibration as a new version of the station's
calibration, not active: an engineer activates it (REST, OPC UA, the page) after reading the
report. One session at a time; a begin drops the one before.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.cameras.base import Frame
from drivers.links.base import HandEyeOutcome
from mvpose_core.calibration.handeye import HandEyeOptions
from mvpose_core.calibration.session import (
    HandEyeCode,
    HandEyeSession,
    SessionError,
    SessionResult,
    holdout_text,
)
from mvpose_core.reasons import Reason

if TYPE_CHECKING:
    from server.station.core import Station

log = logging.getLogger(__name__)

#: how long an add waits for the rig's cameras
GRAB_S = 5.0
DEFAULT_HOLDOUT = 3


@dataclass
class _Open:
    session: HandEyeSession
    folder: Path
    view: int
    begun_by: str
    last: HandEyeOutcome


class HandEye:
    """The station's one hand-eye session; every step on the station loop, one at a time."""

    def __init__(self, station: Station) -> None:
        self.station = station
        self._open: _Open | None = None
        self._lock = asyncio.Lock()
        self.last: HandEyeOutcome = HandEyeOutcome(int(HandEyeCode.NO_SESSION),
                                                   message="no hand-eye session begun")

    # ------------------------------------------------------------------ steps
    async def begin(self, link: str, by: str, holdout: int | None = None) -> HandEyeOutcome:
        async with self._lock:
            return self._note(self._begin(link, by, DEFAULT_HOLDOUT if holdout is None
                                          else holdout))

    async def add_pose(self, link: str, by: str, robot_pose: tuple[float, ...] | None
                       ) -> HandEyeOutcome:
        async with self._lock:
            return self._note(await self._guarded(self._add(link, robot_pose)))

    async def calculate(self, link: str, by: str) -> HandEyeOutcome:
        async with self._lock:
            return self._note(await self._guarded(self._calculate(link, by)))

    async def _guarded(self, step: Awaitable[HandEyeOutcome]) -> HandEyeOutcome:
        """A step that failed unexpectedly (a detector, the store, a bug) is answered FAILED
        with what went wrong, never left to the link as an exception."""
        try:
            return await step
        except Exception as err:  # noqa: BLE001 - the caller gets the reason, the log the trace
            log.exception("hand-eye step failed")
            poses = len(self._open.session.samples) if self._open is not None else 0
            return HandEyeOutcome(int(HandEyeCode.FAILED), poses,
                                  message=f"hand-eye: {type(err).__name__}: {err}")

    def status(self) -> dict[str, Any]:
        """The session as the page and REST show it."""
        o = self._open
        out: dict[str, Any] = {"active": o is not None, "last": _as_dict(self.last)}
        if o is not None:
            s = o.session
            out |= {"rig": s.rig, "board": str(s.board), "cameras": list(s.cameras),
                    "convention": s.convention.value, "poses": len(s.samples),
                    "needed": s.needed, "holdout": s.holdout, "folder": str(o.folder),
                    "begun_by": o.begun_by}
        return out

    # ------------------------------------------------------------------ work
    def _note(self, outcome: HandEyeOutcome) -> HandEyeOutcome:
        self.last = outcome
        if self._open is not None:
            self._open.last = outcome
        (log.info if outcome.code == 0 else log.warning)("hand-eye: %s", outcome.message)
        return outcome

    def _begin(self, link: str, by: str, holdout: int) -> HandEyeOutcome:
        st = self.station
        station = st.station
        fail = int(HandEyeCode.NOT_AVAILABLE)
        if not 0 <= holdout <= 50:  # the PLC's and OPC UA's argument range error
            return HandEyeOutcome(int(Reason.BAD_ARGUMENT),
                                  message=f"hand-eye: holdout must be 0..50, got {holdout}")
        if station.calibration_board is None:
            return HandEyeOutcome(fail, message=(
                f"hand-eye: station {station.name!r} defines no calibration_board in its "
                "station file (e.g. calibration_board: charuco:15x11:40:30)"))
        rigs = [r for r in station.rigs if r.mount == "robot"]
        views = [v.id for v in station.views if rigs and rigs[0].id in v.rigs]
        if not rigs or not views:
            return HandEyeOutcome(fail, message=(
                f"hand-eye: station {station.name!r} has no robot-mounted rig in a view"))
        services = st.measuring.services
        if services is None or st.active is None:
            return HandEyeOutcome(fail, message="hand-eye: the station is not running a recipe")
        from mvpose_core.calibration.boards import BoardSpec
        from mvpose_core.transforms import invert

        rig = rigs[0]
        T_rig = {rc.camera: rc.T_rig_from_cf.matrix for rc in rig.cameras}
        ref = rig.cameras[0].camera
        session = HandEyeSession(
            station.name, rig.id, BoardSpec.parse(station.calibration_board),
            st.active.config.robot_convention,
            {c: station.camera(c).model for c in T_rig},
            {c: invert(T_rig[c]) @ T_rig[ref] for c in T_rig}, T_rig[ref], holdout=holdout,
            options=_options(station))
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%S%fZ")
        folder = Path(services.settings.data_dir) / "handeye" / stamp
        self._open = _Open(session, folder, views[0], by, HandEyeOutcome(0))
        return HandEyeOutcome(0, message=(
            f"hand-eye session {stamp} begun by {by} over {link}: rig {rig.id!r} "
            f"({', '.join(T_rig)}), board {session.board}, poses in the "
            f"{session.convention.value} convention; add at least {session.needed} poses "
            f"({holdout} are held out to check the result)"))

    async def _add(self, link: str, robot_pose: tuple[float, ...] | None) -> HandEyeOutcome:
        o = self._open
        if o is None:
            return HandEyeOutcome(int(HandEyeCode.NO_SESSION),
                                  message="hand-eye: begin a session before adding poses")
        s = o.session
        n = len(s.samples)
        sid = s.next_id()
        try:
            s.pose_of(robot_pose, sid)  # refuse a bad pose before the cameras move
        except SessionError as err:
            return HandEyeOutcome(int(err.code), n, n + 1, message=str(err))
        grabbed = await self.station.triggers.between_async(self._grab, list(s.cameras), o.view)
        failed = {c: str(r) for c, r in grabbed.items() if not isinstance(r, Frame)}
        if failed:
            return HandEyeOutcome(int(HandEyeCode.CAPTURE_FAILED), n, n + 1, message=(
                f"hand-eye pose {sid}: no image from {failed}"))
        images = {c: np.asarray(f.image) for c, f in grabbed.items() if isinstance(f, Frame)}
        dets = await asyncio.to_thread(self._detect, s, o.folder, sid, images)
        try:
            s.add(robot_pose, dets, sid)
        except SessionError as err:
            return HandEyeOutcome(int(err.code), n, n + 1, message=str(err))
        await asyncio.to_thread((o.folder / "poses.csv").write_text, s.poses_csv())
        missed = [c for c, d in dets.items() if d is None]
        seen = ", ".join(f"{c}: {len(d)} corners" for c, d in dets.items() if d is not None)
        return HandEyeOutcome(0, n + 1, n + 1, message=(
            f"hand-eye pose {sid} added ({seen}"
            + (f"; board not found by {missed}" if missed else "") + f"); {n + 1} poses, "
            f"{max(0, s.needed - n - 1)} more needed"))

    def _grab(self, cameras: list[str], view: int) -> dict[str, object]:
        """On the trigger thread: every camera of the rig, at the rig's view."""
        capture = self.station.measuring.capture
        if capture is None:
            return {c: "the cameras are not open" for c in cameras}
        return dict(capture.grab_all(GRAB_S, camera_ids=cameras, view=view))

    @staticmethod
    def _detect(session: HandEyeSession, folder: Path, sid: str,
                images: dict[str, np.ndarray]) -> dict[str, Any]:
        import cv2

        from mvpose_core.calibration.boards import detect

        out: dict[str, Any] = {}
        for cid, image in images.items():
            (folder / cid).mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(folder / cid / f"{sid}.png"), image)
            out[cid] = detect(np.ascontiguousarray(image, dtype=np.uint8), session.board)
        return out

    async def _calculate(self, link: str, by: str) -> HandEyeOutcome:
        o = self._open
        if o is None:
            return HandEyeOutcome(int(HandEyeCode.NO_SESSION),
                                  message="hand-eye: begin a session and add poses first")
        s = o.session
        n = len(s.samples)
        try:
            res = await asyncio.to_thread(self._solve, s, by, o.folder)
        except SessionError as err:
            return HandEyeOutcome(int(err.code), n, message=str(err))
        version = await asyncio.to_thread(self._store, o, res, by, link)
        return HandEyeOutcome(
            0, n, version=version, sigma_mm=res.result.sigma_mm, sigma_deg=res.result.sigma_deg,
            holdout_rms_px=res.holdout_rms_px, holdout_mm=res.holdout_mm,
            holdout_deg=res.holdout_deg, message=(
                f"hand-eye: calibration version {version} stored, waiting for activation: "
                f"1σ {res.result.sigma_mm:.3f} mm / {res.result.sigma_deg:.4f}°, "
                f"{len(res.result.per_sample_rms_px)} poses solved, {len(res.holdout)} held out:"
                f" RMS {res.holdout_rms_px:.3f} px, at most {res.holdout_mm:.3f} mm / "
                f"{res.holdout_deg:.4f}°; report {o.folder / 'report.txt'}"))

    def _solve(self, session: HandEyeSession, by: str, folder: Path) -> SessionResult:
        """Off the loop: the station's calibration (the file's base) and the solve."""
        base = self.station.measuring.active_calibration()
        return session.calculate(by, base[1] if base else None, str(folder))

    def _store(self, o: _Open, res: SessionResult, by: str, link: str) -> int:
        """Write the report beside the images and store the version (off the loop)."""
        from mvpose_core.calibration.report import save_residual_plot
        from server.version_checks import check_calibration

        o.folder.mkdir(parents=True, exist_ok=True)
        text = res.report.text() + "\n" + holdout_text(res.holdout) + "\n"
        (o.folder / "report.txt").write_text(text)
        save_residual_plot(o.folder / "residuals.png", res.report, res.result.residuals)
        services = self.station.measuring.services
        assert services is not None
        station = self.station.file_station
        content = check_calibration(station.name, res.calibration.model_dump(mode="json"),
                                    station)
        info = services.store.versions.add(
            "calibration", station.name, content, by, comment=(
                f"robot-driven hand-eye over {link} ({o.folder.name}): "
                f"{len(res.result.per_sample_rms_px)} poses, hold-out RMS "
                f"{res.holdout_rms_px:.3f} px"))
        return info.version


def _options(station: Any) -> HandEyeOptions:
    """The solve's options: the station's intrinsics held, the robot's per-axis 1σ as ``mvpose
    calibrate handeye`` takes it from a station file (``uncertainty.robot_repeatability``, an
    RSS over three axes), else a good robot's."""
    rep = station.uncertainty.robot_repeatability
    mm, deg = 0.05, 0.01
    if rep is not None and rep.mm > 0 and rep.deg > 0:
        mm, deg = rep.mm / float(np.sqrt(3.0)), rep.deg / float(np.sqrt(3.0))
    return HandEyeOptions(refine_intrinsics=False, robot_sigma_mm=mm, robot_sigma_deg=deg)


def _as_dict(o: HandEyeOutcome) -> dict[str, Any]:
    from dataclasses import asdict

    return asdict(o)
