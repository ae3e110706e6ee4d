"""Grab from every camera of a trigger in parallel, with one deadline and per-camera errors.

Each camera has its own worker thread, so a slow or hung camera costs only its own result: a
grab_all returns by the deadline (plus a small grace for the threads to report) with a Frame or
a DriverError for every camera. A camera whose device is lost is closed and opened again by its
worker in the background, with exponential backoff; until it is back its result is an immediate
DeviceLostError that says when the next attempt is due, and the trigger path never waits for it.

Between triggers, :meth:`CaptureGroup.preview` grabs a frame of each camera for the live
camera view. A trigger preempts it: grab_all tells each camera with a preview in flight to give
way, the preview stops waiting within :data:`PREVIEW_SLICE_S`, drops the exposure it started
(:meth:`Camera.abort`, so that frame never becomes the trigger's) and the trigger's job runs
next on that camera's thread.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Sequence
from concurrent.futures import Future, wait
from dataclasses import dataclass

from drivers.cameras.base import Camera, Frame, TriggerMode
from drivers.errors import DeviceLostError, DriverError, DriverOperationError, DriverTimeout

log = logging.getLogger(__name__)

Result = Frame | DriverError

#: how long a preview waits for its frame between looks at whether a trigger wants the camera
PREVIEW_SLICE_S = 0.002


class PreviewPreemptedError(DriverOperationError):
    """A preview grab gave way to a trigger (its exposure, if it had started one, dropped)."""


@dataclass(frozen=True)
class Backoff:
    """Reconnect delays: ``first_s``, times ``factor`` per failed attempt, at most ``max_s``."""

    first_s: float = 0.1
    factor: float = 2.0
    max_s: float = 5.0

    def __post_init__(self) -> None:
        if not (self.first_s > 0 and self.factor >= 1 and self.max_s >= self.first_s):
            raise ValueError(
                f"backoff needs first_s > 0, factor >= 1, max_s >= first_s, got {self}"
            )

    def delay(self, failures: int) -> float:
        """Seconds to wait before the next attempt after ``failures`` failed ones."""
        return float(min(self.max_s, self.first_s * self.factor ** max(0, failures)))


@dataclass
class _Job:
    t_end: float
    trigger: bool
    future: Future[Result]
    preview: bool = False


class _Worker:
    """One camera's thread: brings the camera up, grabs on request, reconnects when lost."""

    def __init__(self, cam: Camera, trigger: TriggerMode, backoff: Backoff) -> None:
        self.cam = cam
        self.trigger_mode = trigger
        self.backoff = backoff
        self.jobs: queue.SimpleQueue[_Job | None] = queue.SimpleQueue()
        self.current: Future[Result] | None = None  # the last trigger's grab
        self.preview_current: Future[Result] | None = None  # the last preview's grab
        self.preempt = threading.Event()  # a trigger wants the camera: a preview gives way
        self.ready = threading.Event()
        self.down_reason: DriverError | None = None
        self.failures = 0
        self.next_attempt = 0.0  # monotonic time of the next bring-up attempt while down
        self.reconnects = 0
        self.thread = threading.Thread(
            target=self._run, name=f"camera-{cam.camera_id}", daemon=True
        )

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        self._bring_up()
        while True:
            timeout = None
            if self.down_reason is not None:
                timeout = max(0.0, self.next_attempt - time.monotonic())
            try:
                job = self.jobs.get(timeout=timeout)
            except queue.Empty:
                self._bring_up()
                continue
            if job is None:
                return
            if not job.future.set_running_or_notify_cancel():
                continue
            if job.preview:
                job.future.set_result(self._preview(job))
            else:
                self.preempt.clear()  # the trigger's job has the camera now
                job.future.set_result(self._grab(job))

    def _down(self) -> DeviceLostError:
        wait_s = max(0.0, self.next_attempt - time.monotonic())
        return DeviceLostError(
            f"camera {self.cam.camera_id!r}: reconnecting after: {self.down_reason} "
            f"(attempt {self.failures + 1} in {wait_s:.2f} s)"
        )

    def _grab(self, job: _Job) -> Result:
        if self.down_reason is not None:
            return self._down()
        try:
            if job.trigger and self.cam.armed == "software":
                self.cam.trigger()
            return self.cam.grab(max(0.0, job.t_end - time.monotonic()))
        except DeviceLostError as err:
            self._went_down(err)
            return err
        except DriverError as err:
            return err
        except Exception as err:  # a bug must reach the caller as a result, not kill the thread
            wrapped = DriverOperationError(f"camera {self.cam.camera_id!r}: grab failed: {err!r}")
            wrapped.__cause__ = err
            return wrapped

    def _preview(self, job: _Job) -> Result:
        """A frame between triggers: looks every PREVIEW_SLICE_S whether a trigger wants the
        camera, and drops its own exposure when one does (or when the frame is late)."""
        cam = self.cam
        if self.down_reason is not None:
            return self._down()
        if self.preempt.is_set():
            return PreviewPreemptedError(f"camera {cam.camera_id!r}: a trigger came first")
        mode = cam.armed
        if mode == "hardware":
            # Its frames come with the line's hardware triggers: a preview frame would be one.
            return DriverOperationError(
                f"camera {cam.camera_id!r}: hardware-triggered, no frames between triggers"
            )
        try:
            if mode == "software":
                cam.trigger()
            while True:
                left = job.t_end - time.monotonic()
                if self.preempt.is_set() or left <= 0:
                    if mode == "software":
                        cam.abort()
                    if left <= 0:
                        return DriverTimeout(f"camera {cam.camera_id!r}: no preview frame in time")
                    return PreviewPreemptedError(f"camera {cam.camera_id!r}: gave way to a trigger")
                with contextlib.suppress(DriverTimeout):
                    return cam.grab(min(left, PREVIEW_SLICE_S))
        except DeviceLostError as err:
            self._went_down(err)
            return err
        except DriverError as err:
            return err
        except Exception as err:  # a bug must reach the caller as a result, not kill the thread
            wrapped = DriverOperationError(f"camera {cam.camera_id!r}: preview failed: {err!r}")
            wrapped.__cause__ = err
            return wrapped

    def _bring_up(self) -> None:
        """Open, configure and arm the camera; on failure schedule the next attempt."""
        cam = self.cam
        try:
            if self.down_reason is not None:
                with contextlib.suppress(DriverError):  # the old connection is gone either way
                    cam.close()
            if not cam.is_open:
                cam.open()
            if cam.settings is None or self.down_reason is not None:
                cam.configure(cam.settings)
            if cam.armed != self.trigger_mode:
                cam.arm(self.trigger_mode)
        except DriverError as err:
            self.failures += 1 if self.down_reason is not None else 0
            self._went_down(err)
            log.warning(
                "camera %r: bring-up failed (%s); next attempt in %.2f s",
                cam.camera_id,
                err,
                self.next_attempt - time.monotonic(),
            )
            return
        if self.down_reason is not None:
            self.reconnects += 1
            log.info("camera %r: back after %d failed attempts", cam.camera_id, self.failures)
        self.down_reason, self.failures = None, 0
        self.ready.set()

    def _went_down(self, err: DriverError) -> None:
        self.ready.clear()
        self.down_reason = err
        self.next_attempt = time.monotonic() + self.backoff.delay(self.failures)


class CaptureGroup:
    """The cameras of a station, grabbed together; each camera runs in its own thread."""

    def __init__(
        self,
        cameras: Sequence[Camera],
        *,
        trigger: TriggerMode = "software",
        backoff: Backoff | None = None,
        grace_s: float = 0.02,
    ) -> None:
        ids = [c.camera_id for c in cameras]
        if len(set(ids)) != len(ids) or not ids:
            raise ValueError(f"capture group needs cameras with unique ids, got {ids}")
        self.grace_s = grace_s
        self._workers = {c.camera_id: _Worker(c, trigger, backoff or Backoff()) for c in cameras}
        self._closed = False
        # grab_all and preview look at and queue jobs under it: a preview is either queued
        # before a trigger's job (and told to give way) or sees the trigger's job and stays out
        self._queueing = threading.Lock()
        for w in self._workers.values():
            w.thread.start()

    @property
    def camera_ids(self) -> list[str]:
        return list(self._workers)

    def camera(self, camera_id: str) -> Camera:
        return self._workers[camera_id].cam

    def wait_ready(self, timeout_s: float) -> dict[str, DriverError | None]:
        """Wait until every camera is up or ``timeout_s`` passed; the error of each camera down."""
        t_end = time.monotonic() + timeout_s
        for w in self._workers.values():
            w.ready.wait(max(0.0, t_end - time.monotonic()))
        return {
            cid: (
                None
                if w.ready.is_set()
                else w.down_reason or DriverTimeout(f"camera {cid!r}: not up within {timeout_s} s")
            )
            for cid, w in self._workers.items()
        }

    def health(self) -> dict[str, tuple[bool, str | None, int]]:
        """Per camera: (up, why it is down or None, reconnects so far)."""
        return {cid: (w.ready.is_set(), None if w.ready.is_set() or w.down_reason is None
                      else str(w.down_reason), w.reconnects)
                for cid, w in self._workers.items()}

    def status(self) -> dict[str, str]:
        """One line per camera: up, or down with the reason and the reconnects so far."""
        out = {}
        for cid, w in self._workers.items():
            if w.ready.is_set():
                out[cid] = f"up ({w.reconnects} reconnects)"
            else:
                out[cid] = f"down: {w.down_reason}" if w.down_reason else "starting"
        return out

    def grab_all(
        self, deadline_s: float, *, trigger: bool = True, camera_ids: Sequence[str] | None = None,
        view: int | None = None,
    ) -> dict[str, Result]:
        """Trigger (software-armed cameras) and grab every camera; never later than the deadline.

        ``camera_ids`` limits the grab to some cameras (those of one view, say). ``view`` is the
        view the trigger names (:meth:`Camera.at_view`: simulated cameras show it). The result
        has each of them: a Frame, or the DriverError of that camera alone.
        """
        if self._closed:
            raise DriverOperationError("capture group is closed")
        ids = list(self._workers) if camera_ids is None else list(camera_ids)
        unknown = [cid for cid in ids if cid not in self._workers]
        if unknown:
            raise ValueError(
                f"capture group has no cameras {unknown}; it has {list(self._workers)}"
            )
        t_end = time.monotonic() + deadline_s
        if view is not None:
            for cid in ids:  # before any job is queued: each grab then reads this view
                self._workers[cid].cam.at_view(view)
        results: dict[str, Result] = {}
        pending: dict[str, Future[Result]] = {}
        with self._queueing:
            for cid in ids:
                w = self._workers[cid]
                if w.current is not None and not w.current.done():
                    # The previous grab is stuck in a vendor call; queueing behind it would hang.
                    results[cid] = DriverOperationError(
                        f"camera {cid!r}: still busy with the previous grab"
                    )
                    continue
                if w.preview_current is not None and not w.preview_current.done():
                    w.preempt.set()  # the preview gives way; this job runs right after it
                fut: Future[Result] = Future()
                w.current = fut
                w.jobs.put(_Job(t_end, trigger, fut))
                pending[cid] = fut
        wait(pending.values(), timeout=max(0.0, t_end + self.grace_s - time.monotonic()))
        for cid, fut in pending.items():
            if fut.done():
                results[cid] = fut.result()
            else:
                results[cid] = DriverTimeout(f"camera {cid!r}: no answer within {deadline_s:.3f} s")
        return {cid: results[cid] for cid in ids}

    def preview(
        self, deadline_s: float, camera_ids: Sequence[str] | None = None
    ) -> dict[str, Result]:
        """A frame of every camera (or ``camera_ids``) for the live view, by the deadline.

        A camera busy with a trigger's grab or an earlier preview is left out (its result says
        so); a trigger that comes while a preview waits preempts it (PreviewPreemptedError). A
        software-triggered camera is triggered, a free-running one gives its next frame, a
        hardware-triggered one gives none (its frames belong to the line's triggers).
        """
        if self._closed:
            raise DriverOperationError("capture group is closed")
        ids = list(self._workers) if camera_ids is None else list(camera_ids)
        unknown = [cid for cid in ids if cid not in self._workers]
        if unknown:
            raise ValueError(
                f"capture group has no cameras {unknown}; it has {list(self._workers)}"
            )
        t_end = time.monotonic() + deadline_s
        results: dict[str, Result] = {}
        pending: dict[str, Future[Result]] = {}
        with self._queueing:
            for cid in ids:
                w = self._workers[cid]
                busy = [f for f in (w.current, w.preview_current) if f is not None and not f.done()]
                if busy:
                    results[cid] = PreviewPreemptedError(f"camera {cid!r}: busy with a trigger")
                    continue
                fut: Future[Result] = Future()
                w.preview_current = fut
                w.jobs.put(_Job(t_end, True, fut, preview=True))
                pending[cid] = fut
        wait(pending.values(), timeout=max(0.0, t_end + self.grace_s - time.monotonic()))
        for cid, fut in pending.items():
            results[cid] = (
                fut.result()
                if fut.done()
                else DriverTimeout(f"camera {cid!r}: no preview frame within {deadline_s:.3f} s")
            )
        return {cid: results[cid] for cid in ids}

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the workers and close every camera."""
        if self._closed:
            return
        self._closed = True
        for w in self._workers.values():
            w.jobs.put(None)
        t_end = time.monotonic() + timeout_s
        for w in self._workers.values():
            w.thread.join(max(0.0, t_end - time.monotonic()))
            if w.thread.is_alive():
                log.error(
                    "camera %r: worker still blocked in a vendor call after %.1f s",
                    w.cam.camera_id,
                    timeout_s,
                )
                continue
            try:
                w.cam.close()
            except DriverError as err:
                log.warning("camera %r: close failed: %s", w.cam.camera_id, err)

    def __enter__(self) -> CaptureGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
