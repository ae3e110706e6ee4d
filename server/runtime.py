"""The station runtime: cameras, PLC link, active recipes and the pipeline of one station.

Threads, and why:

- ``station-loop``: an asyncio loop of its own holding the Modbus/TCP server (drivers.plc). The
  REST API runs on uvicorn's loop; keeping the PLC link on another loop means no HTTP request
  queued on that loop can delay reading a trigger or publishing a result.
- ``trigger``: one worker that runs every trigger (PLC or REST) in order, so measurements never
  overlap and the robot-mounted sequence needs no lock.
- ``detect-*``: detection worker processes (server.detect_pool) on machines with 4+ cores, or
  threads if asked for; below 4 cores detection runs on the trigger thread (docs/performance.md).
- ``archive``: PNG writes of archived frames, after the PLC has its answer, niced.
- one thread per camera inside drivers.cameras.CaptureGroup.

The runtime is the PLC handler (drivers.plc.seam.PlcHandler): ``measure``, ``select_recipe``,
``teach_reference``, ``reset``. What a trigger does around the pipeline (recipe, view, the
robot-mounted sequence, teaching) is server.triggers; the recipes and their stored versions are
server.recipes.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio.to_thread
import numpy as np
from fastapi import APIRouter

from drivers.cameras import CaptureGroup, make_camera
from drivers.plc import registers
from drivers.plc.seam import PlcConfig, TriggerOutcome, TriggerRequest
from drivers.plc.server import PlcServer
from mvpose_core.station import StationConfig
from server.pipeline import (
    Pipeline,
    PipelineOptions,
    Reason,
    TriggerResult,
)
from server.priority import CollectorPause, TriggerFirst
from server.recipes import ActiveRecipe, RecipeBook
from server.state import Services
from server.triggers import LastResult, TriggerRunner

log = logging.getLogger(__name__)

REST_TRIGGER_ID = 0  # records of commissioning triggers over REST carry trigger id 0


@dataclass(frozen=True)
class RuntimeOptions:
    """How the runtime opens the station's hardware."""

    plc_host: str = "127.0.0.1"
    plc_port: int = 0  # 0 = any free port (tests); 502 or 5020 in production
    plc: PlcConfig | None = None  # default: measure timeout = deadline + 1 s as a backstop
    pipeline: PipelineOptions = field(default_factory=PipelineOptions)
    sim_seed: int = 0  # the simulated scene's generator (kind: sim cameras)
    sim_render: Any = None  # drivers.cameras.RenderOptions for the simulated scene
    camera_ready_s: float = 10.0
    # Simulated cameras: render the part at the recipe's reference pose at start-up, so that a
    # served simulated station has something to measure (tests and the demo move it themselves).
    sim_part_at_reference: bool = False
    # HTTP requests arriving during a trigger wait for it to end, at most this long (0: never):
    # the MES can wait, the PLC cannot (server.priority).
    rest_yield_ms: float = 100.0
    # ... and after a PLC trigger's outcome is ready, until the PLC has read it, at most this
    # long (a PLC task polls every 1-10 ms); the bound of rest_yield_ms still applies.
    answer_read_wait_ms: float = 20.0
    # Python's garbage collector waits while a trigger runs, and what start-up allocated is
    # frozen out of its sight (server.priority.CollectorPause).
    gc_pause: bool = True


def _lower_priority() -> None:
    """Nice the calling thread (Linux: a thread is a task with its own nice value): PNG encoding
    of archived frames releases the GIL and must yield the CPU to the next trigger."""
    # Not Linux, or not permitted: the archive then runs at normal priority.
    with contextlib.suppress(AttributeError, OSError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)


class StationRuntime:
    """One station's hardware and pipeline; the app's Runtime and the PLC's handler."""

    def __init__(self, station: StationConfig, options: RuntimeOptions | None = None) -> None:
        self.station = station
        self.options = options or RuntimeOptions()
        self.services: Services | None = None
        self.scene: Any = None  # drivers.cameras.SimScene when the station has sim cameras
        self.capture: CaptureGroup | None = None
        self.pipeline: Pipeline | None = None
        self.plc: PlcServer | None = None
        self.book: RecipeBook | None = None
        self.runner: TriggerRunner | None = None
        self.started_at: datetime | None = None
        self._trigger_exec: ThreadPoolExecutor | None = None
        self._archive_exec: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._watch: asyncio.Task[None] | None = None
        self.gate = TriggerFirst(self.options.rest_yield_ms / 1000.0)
        self.collector = CollectorPause(self.options.gc_pause)
        self._end_at_answer: Callable[[], None] | None = None  # ends the last trigger's pause
        self.warmed_ms: dict[str, float] = {}  # recipe → how long its start-up warm-up took

    # ------------------------------------------------------------------ app protocol
    def routers(self) -> Sequence[APIRouter]:
        from server.api.station import router

        return [router]

    @asynccontextmanager
    async def lifespan(self, services: Services) -> AsyncIterator[None]:
        self.gate.bind(asyncio.get_running_loop())  # the HTTP server's loop
        await anyio.to_thread.run_sync(self.start, services)
        try:
            yield
        finally:
            await anyio.to_thread.run_sync(self.stop)

    def readiness(self) -> Mapping[str, bool]:
        cams = self.capture.status() if self.capture else {}
        return {
            "cameras": bool(cams) and all(s.startswith("up") for s in cams.values()),
            "plc": self.plc is not None and self._loop is not None,
            "recipe": self.active is not None,
        }

    # ------------------------------------------------------------------ life cycle
    def start(self, services: Services) -> None:
        """Open cameras, load the active recipes, start the trigger thread and the PLC link."""
        if services.station is None or services.station.name != self.station.name:
            raise RuntimeError(
                f"runtime of station {self.station.name!r} needs settings.station to be that "
                f"station's file, got {services.settings.station}")
        self.services = services
        try:
            self._start(services)
        except BaseException:
            self.stop()  # whatever did open (camera threads, pools, the loop) closes again
            raise
        self.started_at = datetime.now(UTC)
        self.collector.freeze()
        assert self.capture is not None
        log.info("station %s: PLC link on %s:%d, cameras %s", self.station.name,
                 self.options.plc_host, self.plc_port, self.capture.status())

    def _start(self, services: Services) -> None:
        calib = self._apply_calibration(services.settings.station)
        self.book = RecipeBook(self.station, services.store)
        self._open_cameras()
        assert self.capture is not None
        self.pipeline = Pipeline(
            self.station, self.capture, services.record_measurement,
            software_version=services.software_version, calibration=calib,
            plan_images=lambda tid, at, ok, cams: services.images.plan(
                self.station.name, tid, at, ok, cams),
            options=self.options.pipeline,
        )
        for recipe in self.book.recipes.values():
            t = time.monotonic()
            try:
                self.pipeline.warm_up(recipe.config)
            except Exception:  # a recipe the engine cannot measure still fails its triggers
                log.warning("recipe %s: warm-up failed", recipe.config.name, exc_info=True)
                continue
            self.warmed_ms[recipe.config.name] = (time.monotonic() - t) * 1e3
        self._trigger_exec = ThreadPoolExecutor(1, thread_name_prefix="trigger")
        self._archive_exec = ThreadPoolExecutor(1, thread_name_prefix="archive",
                                                initializer=_lower_priority)
        self.runner = TriggerRunner(self.station, self.pipeline, self.book, services,
                                    self._archive_exec)
        ready = threading.Event()
        self._thread = threading.Thread(target=self._loop_main, args=(ready,), name="station-loop",
                                        daemon=True)
        self._thread.start()
        ready.wait()
        assert self._loop is not None
        cfg = self.options.plc or PlcConfig(
            measure_timeout_s=self.station.deadline_ms / 1000.0 + 1.0,
            initial_recipe=self.active.number if self.active else 0,
        )
        plc = PlcServer(self, cfg, on_answer_read=self._answer_read)
        asyncio.run_coroutine_threadsafe(
            plc.start(self.options.plc_host, self.options.plc_port), self._loop
        ).result(timeout=10)
        self.plc = plc
        asyncio.run_coroutine_threadsafe(self._start_watch(), self._loop).result(timeout=5)

    def stop(self) -> None:
        """Stop the PLC link, finish the running trigger and archive writes, close the cameras."""
        if self._loop is not None:
            try:
                asyncio.run_coroutine_threadsafe(self._stop_loop_tasks(), self._loop).result(10)
            except Exception:
                log.exception("PLC link did not stop cleanly")
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(timeout=10)
            self._loop = None
        for ex in (self._trigger_exec, self._archive_exec):
            if ex is not None:
                ex.shutdown(wait=True)
        if self.pipeline is not None:
            self.pipeline.close()
        if self.capture is not None:
            self.capture.close()
        self.plc = self.pipeline = self.capture = None
        self.collector.close()

    def _apply_calibration(self, station_file: Path | None) -> tuple[str, str] | None:
        """Put the station's calibration file (if it names one) into the station model.

        A relative path is taken from the station file's folder. A missing or tampered file
        (content hash) stops start-up, naming the file."""
        if not self.station.calibration:
            return None
        from mvpose_core.calibration.files import apply_calibration, load_calibration

        path = Path(self.station.calibration)
        if not path.is_absolute() and station_file is not None:
            path = Path(station_file).parent / path
        calib = load_calibration(path)
        self.station = apply_calibration(self.station, calib)
        log.info("station %s: calibration %s (sha256 %s) from %s", self.station.name, calib.id,
                 calib.sha256[:12], path)
        return calib.id, calib.sha256

    @property
    def plc_port(self) -> int:
        if self.plc is None:
            raise RuntimeError("runtime not started")
        return self.plc.port

    def _loop_main(self, ready: threading.Event) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        self._loop = loop
        ready.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    def _open_cameras(self) -> None:
        scene = None
        if any(c.driver.kind == "sim" for c in self.station.cameras):
            from drivers.cameras import SimScene

            assert self.active is not None
            scene = SimScene(self.station, self.active.config,
                             np.random.default_rng(self.options.sim_seed), self.options.sim_render)
            if self.options.sim_part_at_reference:
                scene.set_part_pose(self.active.config.T_rf_from_pf0.matrix)
        self.scene = scene
        cams = [make_camera(c, scene) for c in self.station.cameras]
        self.capture = CaptureGroup(cams)
        down = {k: v for k, v in self.capture.wait_ready(self.options.camera_ready_s).items() if v}
        for cid, err in down.items():
            log.warning("camera %s not up at start (%s); it keeps reconnecting", cid, err)

    # ------------------------------------------------------------------ recipes
    @property
    def active(self) -> ActiveRecipe | None:
        """The selected recipe."""
        return self.book.selected if self.book else None

    def activate_recipe(self, name: str, version: int | None, by: str) -> ActiveRecipe:
        """Select recipe ``name``; with ``version``, activate that stored version first."""
        assert self.book is not None and self.runner is not None
        self.runner.sequence = []
        return self.book.select(name, version, by)

    def teach_from_measurement(self, measurement_id: int, by: str) -> ActiveRecipe:
        assert self.book is not None
        return self.book.teach_from_measurement(measurement_id, by)

    async def _start_watch(self) -> None:
        self._watch = asyncio.create_task(self._watch_versions(), name="recipe-versions")

    async def _stop_loop_tasks(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
            self._watch = None
        if self.plc is not None:
            await self.plc.stop()

    async def _watch_versions(self, period_s: float = 1.0) -> None:
        """Pick up recipe versions activated through the REST API, between triggers."""
        assert self.book is not None
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(period_s)
            try:
                await loop.run_in_executor(self._trigger_exec, self.book.reload_if_changed)
            except RuntimeError:
                return  # the executor is shut down: the runtime stops
            except Exception:
                log.exception("recipe versions could not be checked")

    # ------------------------------------------------------------------ PLC handler
    def convention_code(self) -> int:
        return self.active.config.robot_convention.code if self.active else 0

    async def select_recipe(self, recipe: int) -> int:
        assert self.book is not None
        found = self.book.by_number(recipe)
        if found is None:
            return int(Reason.UNKNOWN_RECIPE)
        self.activate_recipe(found.config.name, None, "plc")
        return 0

    async def teach_reference(self) -> int:
        self.arm_teach()
        return 0

    def arm_teach(self) -> None:
        """The next final OK result becomes the active recipe's reference."""
        assert self.runner is not None
        self.runner.teach_armed = True

    async def reset(self) -> None:
        assert self.runner is not None
        await asyncio.get_running_loop().run_in_executor(self._trigger_exec,
                                                         self.runner.sequence.clear)

    def measure(self, request: TriggerRequest) -> asyncio.Future[TriggerOutcome]:
        """Start one PLC trigger on the trigger thread now; the future holds its outcome.

        The PLC link calls this as the TRIGGER write arrives, so the HTTP loop's hold and the
        pipeline start before the link has even answered the write.
        """
        t0 = time.monotonic()
        at = datetime.now(UTC)
        loop = asyncio.get_running_loop()
        runner = self.runner
        assert runner is not None
        end = self._pause_for_trigger()

        def release(_: object) -> None:
            # HTTP requests and the collector resume once the PLC has read this outcome (the
            # PLC link calls _answer_read), or answer_read_wait_ms after it is ready at the
            # latest: a REST request let through between the publication and the PLC's next
            # poll would delay that poll's answer (docs/performance.md).
            self._end_at_answer = end
            loop.call_later(self.options.answer_read_wait_ms / 1000.0, end)

        try:
            fut = loop.run_in_executor(self._trigger_exec,
                                       lambda: runner.run(request, t0, at).outcome)
        except BaseException:
            end()  # nothing runs: nothing to wait for
            raise
        fut.add_done_callback(release)
        return fut

    def _pause_for_trigger(self) -> Callable[[], None]:
        """Hold REST requests and the garbage collector for a trigger (server.priority); returns
        the end of the hold, which may be called more than once."""
        self.gate.begin()
        self.collector.begin()
        ended = False

        def end() -> None:
            nonlocal ended
            if not ended:
                ended = True
                self.gate.end()
                self.collector.end()

        return end

    def _answer_read(self) -> None:
        """The PLC link: the PLC has read the last published answer (on the station loop)."""
        end, self._end_at_answer = self._end_at_answer, None
        if end is not None:
            end()

    # ------------------------------------------------------------------ REST entry points
    def trigger(self, part_id: str | None = None, view_index: int = 0,
                timeout_s: float = 10.0) -> TriggerResult:
        """A commissioning trigger over REST: same thread and pipeline as a PLC trigger."""
        if self._trigger_exec is None or self.active is None or self.runner is None:
            raise RuntimeError("runtime not started")
        req = TriggerRequest(trigger_id=REST_TRIGGER_ID, view_index=view_index, robot_pose=None,
                             part_id=part_id or "", recipe=self.active.number)
        end = self._pause_for_trigger()
        try:
            fut: Future[TriggerResult] = self._trigger_exec.submit(
                self.runner.run, req, time.monotonic(), datetime.now(UTC))
            return fut.result(timeout=timeout_s)
        finally:
            end()

    def wait_idle(self, timeout_s: float = 10.0) -> None:
        """Block until every trigger and archive write submitted so far is done (tests, demo)."""
        for ex in (self._trigger_exec, self._archive_exec):
            if ex is not None:
                ex.submit(lambda: None).result(timeout=timeout_s)

    # ------------------------------------------------------------------ status
    @property
    def last(self) -> LastResult | None:
        """The last final result (read by REST threads)."""
        return self.runner.last if self.runner else None

    def status(self) -> dict[str, Any]:
        plc: dict[str, Any] = {"running": self.plc is not None}
        if self.plc is not None:
            st = self.plc.stats
            image = self.plc.input_registers()
            plc.update(
                port=self.plc_port, state=self.plc.state.name, connections=st.connections,
                rejected_connections=st.rejected_connections, timeouts=st.timeouts,
                handler_errors=st.handler_errors, last_errors=list(st.last_errors[-5:]),
                # Heartbeats: ours counts up every tick; the PLC's is watched (ONLINE while it
                # changes within the watchdog time).
                server_heartbeat=image[registers.IR_HEARTBEAT],
                plc_online=bool(image[registers.IR_STATUS] & registers.Status.ONLINE),
                error_code=image[registers.IR_ERROR_CODE],
                watchdog_trips=st.handshake.watchdog_trips,
                missed_triggers=st.handshake.missed_triggers,
            )
        last = self.last
        active = self.active
        runner = self.runner
        return {
            "station": self.station.name,
            "state": self.plc.state.name if self.plc else "STOPPED",
            "started_at": self.started_at,
            "deadline_ms": self.station.deadline_ms,
            "recipe": None if active is None else {
                "name": active.config.name, "version": active.version, "number": active.number,
                "sha256": active.sha256,
            },
            "teach_armed": bool(runner and runner.teach_armed),
            "cameras": self.capture.status() if self.capture else {},
            "plc": plc,
            "counts": dict(runner.counts) if runner else {},
            "sequence_views": [v.view for v in runner.sequence] if runner else [],
            "last_result": None if last is None else last.__dict__,
            # HTTP requests that waited for a running trigger (server.priority), since start
            "rest": {"yield_ms": self.gate.max_wait_s * 1e3,
                     "answer_read_wait_ms": self.options.answer_read_wait_ms,
                     "held_for_triggers": self.gate.held},
            # how long each recipe's start-up warm-up took (Pipeline.warm_up)
            "warm_up_ms": {k: round(v, 1) for k, v in self.warmed_ms.items()},
        }
