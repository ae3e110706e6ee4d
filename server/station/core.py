"""The station: cameras, links, one trigger thread, the pipeline and the record of every answer.

This is everything of the station process (``mvpose station``) except its control channel; it
serves no HTTP. Threads, and why:

- ``station-loop``: an asyncio loop of its own holding the links (Modbus/TCP; the station's side
  of OPC UA, whose server runs in a child process: drivers.links.process) and the control
  channel, so nothing a caller of this object does can delay a trigger's arrival or its answer;
- ``trigger``: one worker runs every trigger (any link, or the control channel) in order, so
  measurements never overlap and the robot-mounted sequence needs no lock;
- ``recorder``: records the answers the station gives without the trigger thread (its watchdog's
  TIMEOUT, a link's own failures), so a stuck trigger thread never stops an answer;
- ``archive``: PNG writes of archived frames, after the link has its answer, niced;
- one thread per camera inside drivers.cameras.CaptureGroup.

Every answer goes through :meth:`Station._answer`: the record is appended first (its seq is the
result id the link publishes), then the link sees the outcome. The station's watchdog answers a
trigger that is not recorded within ``deadline + 1 s`` with a recorded TIMEOUT and makes sure the
late result is never recorded: a link and the store never disagree.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any, Protocol

import numpy as np

from drivers.cameras import CaptureGroup, make_camera
from drivers.links import Link, LinkOutcome, LinkRequest, open_links, relay
from drivers.links.modbus import ModbusLink
from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from mvpose_core.station import StationConfig
from mvpose_core.transforms import RobotConvention
from server.pipeline import Pipeline, PipelineOptions
from server.recipes import ActiveRecipe, RecipeBook
from server.state import Services
from server.station import scheduling
from server.station.queries import StationQueries
from server.station.records import Provenance, failure_record, result_record
from server.station.sequence import Step, ViewSequence
from server.store.events import record_event
from server.store.outbox import OutboxRows
from server.store.schemas import ImageRef, MeasurementRecord

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StationOptions:
    """How the station opens its hardware (the station file says what the hardware is)."""

    pipeline: PipelineOptions = field(default_factory=PipelineOptions)
    sim_seed: int = 0  # the simulated scene's generator (kind: sim cameras)
    sim_render: Any = None  # drivers.cameras.RenderOptions for the simulated scene
    camera_ready_s: float = 10.0
    store_settle_s: float = 5.0  # the longest wait for the journal's zeros ahead before ready
    # Simulated cameras: render the part at the recipe's reference pose at start-up, so that a
    # served simulated station has something to measure (tests and the demo move it themselves).
    sim_part_at_reference: bool = False
    # The watchdog's margin past the deadline: a trigger not recorded by then is answered with
    # a recorded TIMEOUT (the link's own backstop comes a second later).
    answer_margin_s: float = 1.0
    # Listeners (observers: the OPC UA link, whose process gets the result over its socket) hear
    # of a result this long after its append, when the answering link has answered: handing it
    # over holds the GIL.
    observer_delay_s: float = 0.005


@dataclass(frozen=True)
class Appended:
    """A record made durable: its result id (the chain's seq) and its database id, if known."""

    result_id: int
    db_id: int | None
    # calls back with the database id once the record is in the database (at once if it is)
    on_committed: Callable[[Callable[[int], object]], None] | None = None


class RecordSink(Protocol):
    def append(self, record: MeasurementRecord) -> Appended: ...

    def rehearse(self, record: MeasurementRecord) -> None: ...

    def settle(self, timeout_s: float) -> bool: ...

    def status(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class WriterSink:
    """The station's durable writer (server.store.writer): the journal first, the database
    behind it. An append never waits for the database; the database thread inserts a record
    ``commit_delay_s`` after its append, once the link has answered (its ~2 ms of Python would
    otherwise hold the GIL while the answer goes out). With ``outbox`` (the MQTT publisher's),
    each record's messages are inserted in its transaction."""

    def __init__(self, services: Services, commit_delay_s: float = 0.005,
                 outbox: OutboxRows | None = None) -> None:
        from server.store.writer import DurableWriter

        self.services = services
        self.outbox = outbox
        s = services.settings
        self.writer = DurableWriter.open(s.resolved_database_url, services.station_name,
                                         s.data_dir, db_wait_s=0.0,
                                         commit_delay_s=commit_delay_s,
                                         sqlite_synchronous=s.sqlite_synchronous, outbox=outbox)

    def append(self, record: MeasurementRecord) -> Appended:
        sealed = self.writer.append(record)  # StoreFailedError: the station answers STORE_FAILED
        self.services.metrics.observe(record, sealed.seq)
        return Appended(result_id=sealed.seq, db_id=sealed.id, on_committed=sealed.on_committed)

    def rehearse(self, record: MeasurementRecord) -> None:
        self.writer.rehearse(record)

    def settle(self, timeout_s: float) -> bool:
        """Wait for the journal's zeros ahead: the first appends then share the disk with no
        zero piece being written."""
        return self.writer.wait_journal_ahead(timeout_s)

    def status(self) -> dict[str, Any]:
        st = self.writer.status()
        return {"up": st.up, "head_seq": st.head_seq, "committed_seq": st.committed_seq,
                "pending": st.pending, "oldest_pending_s": st.oldest_pending_s,
                "last_error": st.last_error, "conflict": st.conflict, "journal": st.journal}

    def flush(self, timeout_s: float) -> bool:
        return self.writer.flush(timeout_s)

    def close(self) -> None:
        self.writer.close()


@dataclass
class Answer:
    """One trigger's answer as the station gave it, with its record."""

    outcome: LinkOutcome
    record: MeasurementRecord | None
    message: str
    db_id: int | None = None
    on_committed: Callable[[Callable[[int], object]], None] | None = None
    event: ResultEvent | None = None  # the recorded answer's event (None: not recorded)


class _Ticket:
    """One trigger in flight: whoever decides its answer first (the trigger thread recording
    its result, or the watchdog recording TIMEOUT) wins, under the lock."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.state = "running"  # -> "recording" (trigger thread) | "expired" (watchdog)


class Station(StationQueries):
    """One station's hardware, links and pipeline; the links' StationHandler (its queries:
    server.station.queries)."""

    def __init__(self, station: StationConfig, options: StationOptions | None = None) -> None:
        self.file_station = station  # as the station file says, before any calibration
        self.station = station
        self.calibration_version: int | None = None
        self.options = options or StationOptions()
        self.services: Services | None = None
        self.scene: Any = None  # drivers.cameras.SimScene when the station has sim cameras
        self.capture: CaptureGroup | None = None
        self.pipeline: Pipeline | None = None
        self.book: RecipeBook | None = None
        self.sequence: ViewSequence | None = None
        self.sink: RecordSink | None = None
        self.links: list[Link] = []
        self.provenance: Provenance | None = None
        self.started_at: datetime | None = None
        self.warmed_ms: dict[str, float] = {}
        self.counts: dict[str, int] = {"triggers": 0, "ok": 0, "nok": 0, "views": 0}
        self.last: dict[str, Any] | None = None
        self.teach_armed_by: str | None = None
        self._lock = threading.Lock()  # last result and counts, read by the control channel
        self._trigger_exec: ThreadPoolExecutor | None = None
        self._record_exec: ThreadPoolExecutor | None = None
        self._archive_exec: ThreadPoolExecutor | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._watch: asyncio.Task[None] | None = None
        self._listeners: list[Callable[[ResultEvent], None]] = []
        # more parts of the status page, by name (e.g. "mqtt": the plant publisher's status)
        self.status_parts: dict[str, Callable[[], dict[str, Any]]] = {}

    # ------------------------------------------------------------------ life cycle
    def start(self, services: Services, sink: RecordSink | None = None) -> None:
        """Open cameras, load the recipes, warm up, start the trigger thread and the links."""
        if services.station is None or services.station.name != self.station.name:
            raise RuntimeError(
                f"station {self.station.name!r} needs settings.station to be that station's "
                f"file, got {services.settings.station}")
        self.services = services
        try:
            self._start(services, sink or WriterSink(services))
        except BaseException:
            self.stop()  # whatever did open (camera threads, pools, the loop) closes again
            raise
        self.started_at = datetime.now(UTC)
        assert self.capture is not None
        log.info("station %s: links %s, cameras %s", self.station.name,
                 {lk.name: lk.status().get("port") for lk in self.links}, self.capture.status())

    def _start(self, services: Services, sink: RecordSink) -> None:
        calib = self._apply_calibration()
        self.provenance = Provenance(self.station.name, services.software_version, calib)
        self.sink = sink
        self.book = RecipeBook(self.station, services.store)
        self._open_cameras()
        assert self.capture is not None
        self.pipeline = Pipeline(self.station, self.capture, options=self.options.pipeline)
        for recipe in self.book.recipes.values():
            t = time.monotonic()
            try:
                self.pipeline.warm_up(recipe.config)
            except Exception:  # a recipe the engine cannot measure still fails its triggers
                log.warning("recipe %s: warm-up failed", recipe.config.name, exc_info=True)
                continue
            self.warmed_ms[recipe.config.name] = (time.monotonic() - t) * 1e3
        self.sequence = ViewSequence(self.station, self.pipeline, self.book)
        self._trigger_exec = ThreadPoolExecutor(1, thread_name_prefix="trigger")
        self._record_exec = ThreadPoolExecutor(1, thread_name_prefix="recorder")
        self._archive_exec = ThreadPoolExecutor(1, thread_name_prefix="archive",
                                                initializer=scheduling.background)
        for pool in (self._trigger_exec, self._record_exec, self._archive_exec):
            pool.submit(int).result()  # each thread exists before the first trigger needs it
        if self.book.recipes:  # a record built and sealed as an append does, nothing kept
            for _ in range(8):
                sink.rehearse(failure_record(
                    self.provenance, code=int(Reason.INTERNAL_ERROR), message="rehearsal",
                    trigger_id=0, part_id=None, triggered_at=datetime.now(UTC),
                    recipe=self._any_recipe(), total_ms=0.0))
        if not sink.settle(self.options.store_settle_s):
            log.warning("station %s: the store's journal has not written its space ahead "
                        "within %.1f s; the first appends grow the file", self.station.name,
                        self.options.store_settle_s)
        self._loop, self._thread = _loop_thread("station-loop")
        # an OPC UA link's process imports asyncua before it answers (seconds on a loaded host)
        self.run_on_loop(self._start_links(), timeout=30)

    async def _start_links(self) -> None:
        margin = self.options.answer_margin_s
        configs: dict[str, Any] = {}
        for name in type(self.station.links).model_fields:  # one block per backend
            cfg = getattr(self.station.links, name)
            if cfg is None:
                continue
            if getattr(cfg, "measure_timeout_s", 0) is None:  # a backstop behind the watchdog
                cfg = cfg.model_copy(update={
                    "measure_timeout_s": self.station.deadline_ms / 1000.0 + margin + 1.0})
            if getattr(cfg, "pki_dir", "") is None and self.services is not None:
                # certificates (OPC UA) live in the data directory, with the store
                cfg = cfg.model_copy(update={
                    "pki_dir": str(self.services.settings.data_dir / name)})
            configs[name] = cfg
        self.links = open_links(configs, self)
        for link in self.links:
            await link.start()
        self._watch = asyncio.create_task(self._watch_versions(), name="recipe-versions")

    def stop(self) -> None:
        """Stop the links, finish the running trigger and archive writes, close the cameras."""
        if self._loop is not None:
            try:
                self.run_on_loop(self._stop_loop_tasks(), timeout=10)
            except Exception:
                log.exception("links did not stop cleanly")
            self._loop.call_soon_threadsafe(self._loop.stop)
            if self._thread is not None:
                self._thread.join(timeout=10)
            self._loop = None
        for ex in (self._trigger_exec, self._record_exec, self._archive_exec):
            if ex is not None:
                ex.shutdown(wait=True, cancel_futures=True)
        self._trigger_exec = self._record_exec = self._archive_exec = None
        if self.pipeline is not None:
            self.pipeline.close()
        if self.capture is not None:
            self.capture.close()
        self.pipeline = self.capture = None
        if self.sink is not None:
            self.sink.close()  # what the database did not take yet stays in the journal
            self.sink = None

    async def _stop_loop_tasks(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
            self._watch = None
        for link in self.links:
            await link.stop()
        self.links = []

    def run_on_loop(self, coro: Any, timeout: float | None = None) -> Any:
        """Run a coroutine on the station loop from another thread and wait for its result."""
        if self._loop is None:
            coro.close()
            raise RuntimeError("the station is not running")
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        return self._loop

    def _active_calibration(self) -> tuple[int, Any] | None:
        """The store's active version of the calibration named after the station (seeded from
        the station file's ``calibration:`` at start-up, replaced by REST uploads): (version,
        CalibrationFile), or None when the station has none."""
        from mvpose_core.calibration.files import CalibrationFile
        from server.errors import NotFoundError

        assert self.services is not None
        try:
            info, content = self.services.store.versions.content("calibration",
                                                                 self.file_station.name)
        except NotFoundError:
            return None
        return info.version, CalibrationFile.model_validate(content)

    def _apply_calibration(self) -> tuple[str, str] | None:
        """Put the active calibration into the station model (from the station file's model,
        so one calibration never stacks on another)."""
        from mvpose_core.calibration.files import apply_calibration

        active = self._active_calibration()
        self.calibration_version = active[0] if active else None
        if active is None:
            self.station = self.file_station
            return None
        version, calib = active
        self.station = apply_calibration(self.file_station, calib)
        log.info("station %s: calibration %s (sha256 %s), version %d", self.station.name,
                 calib.id, calib.sha256[:12], version)
        return calib.id, calib.sha256

    def _reload_calibration(self) -> bool:
        """On the trigger thread: a calibration version activated through the API is measured
        with from the next trigger on (the pipeline is built again and warmed up)."""
        assert self.capture is not None and self.book is not None
        active = self._active_calibration()
        if (active[0] if active else None) == self.calibration_version:
            return False
        calib = self._apply_calibration()
        old = self.pipeline
        pipeline = Pipeline(self.station, self.capture, options=self.options.pipeline)
        for recipe in self.book.recipes.values():
            with contextlib.suppress(Exception):  # two passes: a trigger may be waiting
                pipeline.warm_up(recipe.config, passes=2)
        self.pipeline = pipeline
        self.sequence = ViewSequence(self.station, pipeline, self.book)
        assert self.provenance is not None
        self.provenance = replace(self.provenance, calibration=calib)
        if old is not None:
            old.close()
        return True

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

    async def _watch_versions(self, period_s: float = 1.0) -> None:
        """Pick up recipe versions activated through the API, between triggers."""
        assert self.book is not None
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(period_s)
            try:
                changed = await loop.run_in_executor(self._trigger_exec, self._reload_recipes)
            except RuntimeError:
                return  # the executor is shut down: the station stops
            except Exception:
                log.exception("recipe versions could not be checked")
                continue
            if changed:
                self._recipe_changed()

    def _reload_recipes(self) -> bool:
        """Recipe and calibration versions activated elsewhere; True when something changed."""
        assert self.book is not None
        before = {n: r.version for n, r in self.book.recipes.items()}
        self.book.reload_if_changed()
        calibrated = self._reload_calibration()
        return calibrated or before != {n: r.version for n, r in self.book.recipes.items()}

    # ------------------------------------------------------------------ recipes
    @property
    def active(self) -> ActiveRecipe | None:
        """The selected recipe."""
        return self.book.selected if self.book else None

    def _recipe_changed(self) -> None:
        if self._loop is None:
            return
        for link in self.links:
            self._loop.call_soon_threadsafe(link.recipe_changed)

    # ------------------------------------------------------------------ StationHandler (links)
    def convention(self) -> RobotConvention:
        active = self.active
        return active.config.robot_convention if active else RobotConvention.FANUC

    def selected_recipe(self) -> int:
        active = self.active
        return active.number if active else 0

    async def select_recipe(self, number: int) -> int:
        assert self.book is not None
        found = self.book.by_number(number)
        if found is None:
            return int(Reason.UNKNOWN_RECIPE)
        await asyncio.get_running_loop().run_in_executor(
            self._trigger_exec, self._select, found.config.name, None, "plc")
        self._recipe_changed()  # every link shows it (Modbus: INITIALIZED -> READY)
        return 0

    def _select(self, name: str, version: int | None, by: str) -> ActiveRecipe:
        assert self.book is not None and self.sequence is not None
        self.sequence.clear()
        return self.book.select(name, version, by)

    async def teach_reference(self, by: str) -> int:
        self.teach_armed_by = by
        return 0

    async def reset(self) -> None:
        assert self.sequence is not None
        await asyncio.get_running_loop().run_in_executor(self._trigger_exec, self.sequence.clear)

    def measure(self, request: LinkRequest) -> asyncio.Future[LinkOutcome]:
        """Start one trigger on the trigger thread now (on the station loop); the future holds
        its outcome, recorded, within the deadline + answer_margin_s."""
        out: asyncio.Future[LinkOutcome] = asyncio.get_running_loop().create_future()
        relay(self.measure_answer(request), out, lambda answer: answer.outcome)
        return out

    def measure_answer(self, request: LinkRequest) -> asyncio.Future[Answer]:
        """:meth:`measure` with the record and the message (the control channel's trigger)."""
        t0 = time.monotonic()
        at = datetime.now(UTC)
        loop = asyncio.get_running_loop()
        ticket = _Ticket()
        out: asyncio.Future[Answer] = loop.create_future()
        work = loop.run_in_executor(self._trigger_exec, self._run, request, t0, at, ticket)


        def expire() -> None:
            with ticket.lock:
                if ticket.state != "running":
                    return  # being recorded: the append never takes long
                ticket.state = "expired"
            limit = self.station.deadline_ms / 1000.0 + self.options.answer_margin_s
            text = (f"no result within {limit * 1e3:.0f} ms (the deadline plus "
                    f"{self.options.answer_margin_s * 1e3:.0f} ms): the trigger thread is stuck")
            log.warning("trigger %d: %s", request.trigger_id, text)
            rec = loop.run_in_executor(self._record_exec, self._record_failure, request,
                                       int(Reason.TIMEOUT), text, (time.monotonic() - t0) * 1e3,
                                       at)
            relay(rec, out, lambda answer: answer)

        limit_s = self.station.deadline_ms / 1000.0 + self.options.answer_margin_s
        watchdog = loop.call_later(limit_s, expire)
        work.add_done_callback(lambda _: watchdog.cancel())
        relay(work, out, lambda answer: answer)  # None: the watchdog has answered
        return out

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        """A link's own answer (its backstop timeout, a failed handler), recorded."""
        loop = asyncio.get_running_loop()
        answer = await loop.run_in_executor(self._record_exec, self._record_failure, request,
                                            code, message, processing_ms, datetime.now(UTC))
        return answer.outcome.result_id

    # ------------------------------------------------------------------ the trigger thread
    def _run(self, req: LinkRequest, t0: float, at: datetime,
             ticket: _Ticket) -> Answer | None:
        assert self.sequence is not None and self.provenance is not None
        with self._lock:
            self.counts["triggers"] += 1
        try:
            step = self.sequence.run(req, t0)
        except Exception as err:  # a bug: still one answer, recorded
            log.exception("trigger %d failed", req.trigger_id)
            step = None
            refused: tuple[int, str] = (int(Reason.INTERNAL_ERROR),
                                        f"{type(err).__name__}: {err}")
        if step is not None and not step.final:
            with self._lock:
                self.counts["views"] += 1
            return Answer(LinkOutcome(0, 0, views_done=step.views_done, final=False,
                                      processing_ms=(time.monotonic() - t0) * 1e3),
                          None, "view done")
        with ticket.lock:
            if ticket.state == "expired":
                log.warning("trigger %d: its result came after the watchdog's TIMEOUT and is "
                            "not recorded", req.trigger_id)
                return None
            ticket.state = "recording"
        recipe = step.recipe if step is not None else self._any_recipe()
        images: list[ImageRef] = []
        if step is not None and step.result is not None:
            res = step.result
            if self.services is not None:
                images = self.services.images.plan(self.station.name, req.trigger_id, at, res.ok,
                                                   sorted(res.frames))
            record = result_record(self.provenance, res, trigger_id=req.trigger_id,
                                   part_id=req.part_id or None, triggered_at=at, recipe=recipe,
                                   images=images)
            message = res.message
        else:
            code, message = step.refused if step is not None and step.refused else refused
            record = failure_record(self.provenance, code=code, message=message,
                                    trigger_id=req.trigger_id, part_id=req.part_id or None,
                                    triggered_at=at, recipe=recipe,
                                    total_ms=(time.monotonic() - t0) * 1e3)
        answer = self._append(record, message, t0, req.link)
        archiving = False
        if step is not None and step.result is not None and answer.record is not None:
            archiving = self._after(step, answer)
        if images and not archiving and self.services is not None:
            self.services.images.release()  # the record was not stored: no frames to write
        return answer

    def _any_recipe(self) -> ActiveRecipe:
        assert self.book is not None
        return self.book.selected or next(iter(self.book.recipes.values()))

    def _record_failure(self, req: LinkRequest, code: int, message: str, total_ms: float,
                        at: datetime) -> Answer:
        assert self.provenance is not None
        if self.sequence is not None:
            self.sequence.clear()  # a failed trigger ends any multi-view sequence
        record = failure_record(self.provenance, code=code, message=message,
                                trigger_id=req.trigger_id, part_id=req.part_id or None,
                                triggered_at=at, recipe=self._any_recipe(), total_ms=total_ms)
        return self._append(record, message, time.monotonic() - total_ms / 1e3, req.link)

    def _append(self, record: MeasurementRecord, message: str, t0: float,
                link: str = "") -> Answer:
        """Make ``record`` durable, then build the link's outcome from it (the same code)."""
        assert self.sink is not None
        t = time.monotonic()
        try:
            done = self.sink.append(record)
        except Exception as err:
            log.exception("trigger %d: the record could not be stored", record.trigger_id)
            code = int(Reason.STORE_FAILED)
            return Answer(LinkOutcome(code, 0, processing_ms=(time.monotonic() - t0) * 1e3),
                          None, f"the record could not be stored: {err}")
        if self.pipeline is not None:
            self.pipeline.note_append_ms((time.monotonic() - t) * 1e3)
        event = record_event(record, done.result_id)
        outcome = LinkOutcome.from_event(event, processing_ms=(time.monotonic() - t0) * 1e3)
        with self._lock:
            self.counts["ok" if event.ok else "nok"] += 1
            self.last = {  # the status page's last result: the event, and how it was answered
                **event.to_dict(), "measurement_id": done.db_id, "link": link,
                "message": message, "processing_ms": outcome.processing_ms,
                "at": record.triggered_at.isoformat(),
                "offset": list(outcome.offset) if outcome.offset is not None else None,
                "sigma_mm": outcome.sigma_trans_mm, "sigma_deg": outcome.sigma_rot_deg,
            }
        if done.db_id is None and done.on_committed is not None:
            done.on_committed(lambda db_id: self._committed(done.result_id, db_id))
        if self._listeners:
            self._tell_later(event)
        answer = Answer(outcome, record, message, done.db_id, event=event)
        answer.on_committed = done.on_committed
        return answer

    def _tell_later(self, event: ResultEvent) -> None:
        """Call the listeners with ``event`` observer_delay_s from now, on the station loop (at
        once on this thread when there is no loop to wait on)."""
        loop, delay = self._loop, self.options.observer_delay_s
        if loop is not None and delay > 0:
            with contextlib.suppress(RuntimeError):  # the loop closed: tell them now
                loop.call_soon_threadsafe(loop.call_later, delay, self._tell, event)
                return
        self._tell(event)

    def _tell(self, event: ResultEvent) -> None:
        for listen in list(self._listeners):
            try:
                listen(event)
            except Exception:
                log.exception("a result listener failed")

    def _committed(self, result_id: int, db_id: int) -> None:
        with self._lock:
            if self.last is not None and self.last["result_id"] == result_id:
                self.last["measurement_id"] = db_id

    def _after(self, step: Step, answer: Answer) -> bool:
        """Teach if armed; hand the record's planned frames to the archive (True if it has)."""
        rec = answer.record
        assert rec is not None and step.result is not None and self.book is not None
        if self.teach_armed_by is not None and rec.result == "OK" and rec.T_rf_from_pf is not None:
            by, self.teach_armed_by = self.teach_armed_by, None
            self.book.teach(step.recipe.config.name, np.array(rec.T_rf_from_pf), by,
                            f"taught by {by} from trigger {rec.trigger_id} "
                            f"(result {answer.outcome.result_id})")
            self._recipe_changed()
        archive = self._archive_exec
        if rec.images and archive is not None and answer.on_committed is not None:
            frames = step.result.frames
            # The archive's rows name the record's database id: written once the database has
            # the record (at once, unless the database is slow or down).
            def write(db_id: int) -> None:
                try:
                    archive.submit(self._archive, db_id, rec, frames)
                except RuntimeError:  # the station stopped meanwhile
                    assert self.services is not None
                    self.services.images.release()

            answer.on_committed(write)
            return True
        return False

    def _archive(self, measurement_id: int, rec: MeasurementRecord,
                 frames: Mapping[tuple[int, str], np.ndarray]) -> None:
        assert self.services is not None
        try:
            self.services.images.write(measurement_id, rec.images, rec.result == "OK", frames)
        except Exception:
            log.exception("measurement %d: archiving its frames failed", measurement_id)

    # ------------------------------------------------------------------ control (any thread)
    def trigger(self, part_id: str | None = None, view_index: int = 0,
                trigger_id: int = 0, timeout_s: float = 10.0) -> Answer:
        """A commissioning trigger (control channel): the same thread and record as any link."""
        if self._loop is None or self.active is None:
            raise RuntimeError("the station is not running")
        req = LinkRequest(link="rest", trigger_id=trigger_id, view_index=view_index,
                          robot_pose=None, part_id=part_id or "", recipe=0)

        async def run() -> Answer:
            return await self.measure_answer(req)

        result: Answer = self.run_on_loop(run(), timeout=timeout_s)
        return result

    def arm_teach(self, by: str) -> ActiveRecipe:
        """The next final OK result becomes the selected recipe's reference."""
        assert self.active is not None
        self.teach_armed_by = by
        return self.active

    def teach_from_measurement(self, measurement_id: int, by: str) -> ActiveRecipe:
        assert self.book is not None
        rec = self._on_trigger_thread(self.book.teach_from_measurement, measurement_id, by)
        self._recipe_changed()
        return rec

    def activate_recipe(self, name: str, version: int | None, by: str) -> ActiveRecipe:
        """Select recipe ``name``; with ``version``, activate that stored version first."""
        rec: ActiveRecipe = self._on_trigger_thread(self._select, name, version, by)
        self._recipe_changed()
        return rec

    def reload_recipes(self) -> bool:
        """Pick up versions activated through the API now (else within a second)."""
        changed: bool = self._on_trigger_thread(self._reload_recipes)
        if changed:
            self._recipe_changed()
        return changed

    def _on_trigger_thread(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Between triggers: a recipe never changes under a running measurement."""
        if self._trigger_exec is None:
            raise RuntimeError("the station is not running")
        return self._trigger_exec.submit(fn, *args).result(timeout=30)

    def wait_idle(self, timeout_s: float = 10.0) -> None:
        """Block until every trigger, database commit and archive write submitted so far is
        done (tests, demo)."""
        for ex in (self._trigger_exec, self._record_exec):
            if ex is not None:
                ex.submit(lambda: None).result(timeout=timeout_s)
        flush = getattr(self.sink, "flush", None)
        if flush is not None:
            flush(timeout_s)
        if self._archive_exec is not None:
            self._archive_exec.submit(lambda: None).result(timeout=timeout_s)

    def add_listener(self, listen: Callable[[ResultEvent], None]) -> None:
        """Call ``listen(event)`` after each recorded answer, observer_delay_s after its
        append, on the station loop's thread."""
        self._listeners.append(listen)

    # ------------------------------------------------------------------ status
    @property
    def modbus(self) -> ModbusLink | None:
        return next((lk for lk in self.links if isinstance(lk, ModbusLink)), None)

    @property
    def plc_port(self) -> int:
        link = self.modbus
        if link is None:
            raise RuntimeError("the station has no Modbus link running")
        return link.port

    def readiness(self) -> dict[str, bool]:
        cams = self.capture.status() if self.capture else {}
        return {
            "cameras": bool(cams) and all(s.startswith("up") for s in cams.values()),
            "links": bool(self.links) and all(lk.ready() for lk in self.links),
            "recipe": self.active is not None,
        }

    def status(self) -> dict[str, Any]:
        active = self.active
        modbus = self.modbus
        with self._lock:
            last = None if self.last is None else dict(self.last)
            counts = dict(self.counts)
        return {
            "station": self.station.name,
            "state": modbus.status()["state"] if modbus and modbus.server else "STOPPED",
            "pid": os.getpid(),
            "started_at": self.started_at.isoformat() if self.started_at else None,
            "deadline_ms": self.station.deadline_ms,
            "recipe": None if active is None else {
                "name": active.config.name, "version": active.version, "number": active.number,
                "sha256": active.sha256, "convention": active.config.robot_convention.value,
            },
            "calibration": None if not self.provenance or not self.provenance.calibration else {
                "id": self.provenance.calibration[0], "sha256": self.provenance.calibration[1],
                "version": self.calibration_version},
            "teach_armed": self.teach_armed_by is not None,
            "cameras": self.capture.status() if self.capture else {},
            "links": {lk.name: lk.status() for lk in self.links},
            "plc": modbus.status() if modbus else {"running": False},
            "counts": counts,
            "sequence_views": [v.view for v in self.sequence.views] if self.sequence else [],
            "last_result": last,
            "warm_up_ms": {k: round(v, 1) for k, v in self.warmed_ms.items()},
            "store": self.sink.status() if self.sink is not None else None,
            "archive": self.services.images.status() if self.services is not None else None,
            **{name: part() for name, part in self.status_parts.items()},
        }


def _loop_thread(name: str) -> tuple[asyncio.AbstractEventLoop, threading.Thread]:
    """A new event loop running in a daemon thread of its own (stopped with ``loop.stop``)."""
    loop = asyncio.new_event_loop()

    def main() -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            loop.close()

    thread = threading.Thread(target=main, name=name, daemon=True)
    thread.start()
    return loop, thread
