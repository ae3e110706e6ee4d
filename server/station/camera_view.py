"""The live camera view's frames: grabbed between triggers, on request, at most twice a second.

The API process asks (control channel ``camera_view``) only while a browser has the view open,
so nothing is grabbed when nobody looks. Each request returns the newest frame set; a set older
than :data:`PERIOD_S` is replaced by a new grab first, so however many viewers or API
processes ask, the cameras give at most one preview frame per period.

What keeps the trigger path from waiting: a grab is not started while a trigger runs; a trigger
that comes during a grab preempts it on each camera's own thread (CaptureGroup.preview: the
preview gives way within 2 ms and drops the exposure it started); the picture and the figures
cost ~2 ms of CPU per camera (every k-th pixel, the light figures from a sample, the focus over
the mark windows: mvpose_core.image_figures) and run on this room's own thread at real-time
priority 1, below the trigger path's (scheduling.beneath): a trigger takes the core from it at
once, and no normal task keeps it from giving the GIL back (the niced thread it first ran on
did: bench observers, p99 1.5 times the baseline). The pixel loops are numpy's and libjpeg's on
this thread itself: OpenCV's parallel functions would hand them to OpenCV's thread pool, whose
threads the trigger path started and which therefore run at its priority.
"""

from __future__ import annotations

import asyncio
import base64
import logging
import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from typing import Any

import cv2

from drivers.cameras import Frame
from drivers.cameras.capture import PreviewPreemptedError
from mvpose_core.detect import DetectOptions, predict_marks
from mvpose_core.image_figures import Window, downscale, image_figures
from mvpose_core.scene import view_cameras
from server.errors import ConflictError
from server.station import scheduling
from server.station.measuring import Measuring
from server.station.messages import CameraViewAnswer, CameraViewFrame

log = logging.getLogger(__name__)

#: at most one frame set per period (the issue: at most 2 frames per second)
PERIOD_S = 0.5
#: how long a preview waits for its frames (a simulated or real exposure and transfer)
GRAB_DEADLINE_S = 1.0
JPEG_QUALITY = 80
_DETECT = DetectOptions()


class CameraView:
    """The newest preview frame set of the station's cameras and what it cost."""

    def __init__(self, measuring: Measuring, trigger_running: Any) -> None:
        self.measuring = measuring
        self._trigger_running = trigger_running  # () -> bool: a trigger is being measured now
        self._exec: ThreadPoolExecutor | None = None
        self._lock = threading.Lock()
        self._last: CameraViewAnswer | None = None
        self._last_t = -math.inf
        self._frames: dict[str, CameraViewFrame] = {}
        self._windows: dict[tuple[Any, ...], dict[str, list[Window]]] = {}
        self.counts = {"requests": 0, "grabs": 0, "frames": 0, "preempted": 0, "skipped": 0}
        self.last_grab_at: str | None = None
        self.grabbing = False  # a request is being answered (a preview may be in flight)

    def close(self) -> None:
        ex, self._exec = self._exec, None
        if ex is not None:
            ex.shutdown(wait=True, cancel_futures=True)

    def status(self) -> dict[str, Any]:
        """The station status's ``camera_view`` part: requests, frame sets grabbed, camera
        frames given way to a trigger, sets skipped because a trigger ran, the last grab."""
        return {**self.counts, "grabbing": self.grabbing, "last_grab_at": self.last_grab_at,
                "period_s": PERIOD_S}

    async def frames(self, width: int) -> CameraViewAnswer:
        """:meth:`take` on this room's thread (never on the station loop)."""
        if self._exec is None:
            self._exec = ThreadPoolExecutor(1, thread_name_prefix="camera-view",
                                            initializer=scheduling.beneath)
        return await asyncio.get_running_loop().run_in_executor(self._exec, self.take, width)

    # ------------------------------------------------------------------ its thread
    def take(self, width: int) -> CameraViewAnswer:
        """The newest frame set, grabbed first when it is older than PERIOD_S. ``grabbing`` is
        true from the request's arrival to its answer, the frames' figures included."""
        with self._lock:
            self.grabbing = True
            try:
                return self._take(width)
            finally:
                self.grabbing = False

    def _take(self, width: int) -> CameraViewAnswer:
        self.counts["requests"] += 1
        now = time.monotonic()
        if self._last is not None and self._last.cameras and now - self._last_t < PERIOD_S:
            return self._last
        capture = self.measuring.capture
        if capture is None:
            raise ConflictError("the station's cameras are not open")
        if self._trigger_running():
            self.counts["skipped"] += 1
            self._last_t = now  # look again a period later, not at once
            return self._answer("a trigger is running: the frames shown are older")
        results = capture.preview(GRAB_DEADLINE_S)
        self._last_t = time.monotonic()
        self.counts["grabs"] += 1
        self.last_grab_at = datetime.now(UTC).isoformat()
        windows = self._mark_windows()
        for cid, res in results.items():
            self._frames[cid] = self._frame(cid, res, width, windows.get(cid, []))
        return self._answer("")

    def _answer(self, note: str) -> CameraViewAnswer:
        capture = self.measuring.capture
        ids = capture.camera_ids if capture is not None else list(self._frames)
        cams = [self._frames.get(cid) or _empty(cid, "no frame yet") for cid in ids]
        self._last = CameraViewAnswer(seq=self.counts["grabs"], period_s=PERIOD_S,
                                      cameras=cams, note=note)
        return self._last

    def _frame(self, cid: str, res: Frame | Exception, width: int,
               windows: list[Window]) -> CameraViewFrame:
        if not isinstance(res, Frame):
            if isinstance(res, PreviewPreemptedError):
                self.counts["preempted"] += 1
            old = self._frames.get(cid)
            note = f"not new: {res}"
            return old.model_copy(update={"note": note}) if old else _empty(cid, note)
        self.counts["frames"] += 1
        fig = image_figures(res.image, windows)
        small = downscale(res.image, width)
        ok, jpeg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:  # OpenCV failed to encode a mono8 image: say so instead of showing nothing
            return _empty(cid, "the frame could not be encoded as JPEG")
        return CameraViewFrame(
            camera_id=cid, jpeg_base64=base64.b64encode(jpeg.tobytes()).decode("ascii"),
            width=int(small.shape[1]), height=int(small.shape[0]),
            grabbed_at=datetime.now(UTC).isoformat(), focus=round(fig.focus, 2),
            focus_area=fig.focus_area, mean=round(fig.mean, 2),
            saturated_pct=round(fig.saturated_pct, 3), dark_pct=round(fig.dark_pct, 3), note="")

    def _mark_windows(self) -> dict[str, list[Window]]:
        """Each camera's mark windows in its image: the detector's search windows of the
        selected recipe at its taught reference, in the first view the camera sees marks in."""
        m = self.measuring
        active = m.active
        if active is None:
            return {}
        capture = m.capture
        key = (id(m.station), active.config.name, active.version)
        hit = self._windows.get(key)
        if hit is not None:
            return hit
        out: dict[str, list[Window]] = {}
        for cam in view_cameras(m.station):
            if cam.camera_id in out:
                continue
            wins: list[Window] = []
            for p in predict_marks(cam, active.config, active.config.T_rf_from_pf0.matrix,
                                   _DETECT.size_tolerance, _DETECT.shape_slack_deg):
                half = p.max_shift_px + p.radius_range[1] + _DETECT.window_extra_px
                u, v = float(p.uv[0]), float(p.uv[1])
                wins.append((int(u - half), int(v - half), int(u + half) + 1, int(v + half) + 1))
            settings = capture.camera(cam.camera_id).settings if capture is not None else None
            if settings is not None:  # a region of the sensor: windows in the region's pixels
                dx, dy = settings.offset_x, settings.offset_y
                wins = [(a - dx, b - dy, c - dx, d - dy) for a, b, c, d in wins]
            if wins:
                out[cam.camera_id] = wins
        if len(self._windows) > 16:
            self._windows.clear()
        self._windows[key] = out
        return out


def _empty(cid: str, note: str) -> CameraViewFrame:
    return CameraViewFrame(camera_id=cid, jpeg_base64=None, width=0, height=0, grabbed_at=None,
                           focus=None, focus_area="", mean=None, saturated_pct=None,
                           dark_pct=None, note=note)
