"""The station: cameras, links, one trigger thread, the pipeline and the record of every answer.

This is everything of the station process (``mvpose station``) except its control channel; it
serves no HTTP. :class:`Station` is the façade that wires its rooms, each with one purpose:

- :mod:`server.station.measuring`: what it measures with (calibrated station model, cameras,
  pipeline, recipe book, view sequence, an armed teach);
- :mod:`server.station.triggers`: the ``trigger`` thread, the deadline's watchdog and the
  ``recorder`` thread that answers without it;
- :mod:`server.station.recorder`: appending each answer's record (the sink:
  :mod:`server.station.sink`), the counts and last result, the listeners and the ``archive``
  thread;
- :mod:`server.station.links`: the ``station-loop`` thread and the links on it;
- :mod:`server.station.queries`: what a link may read from the store.

It implements the links' :class:`drivers.links.base.StationHandler` by delegating to them, and
offers the control channel's operations (server.station.control). One thread per camera runs
inside drivers.cameras.CaptureGroup.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import threading
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from drivers.links import Link, LinkOutcome, LinkRequest
from drivers.links.base import (
    CalibrationInfo,
    HandEyeOutcome,
    RecipeInfo,
    ResultQuery,
    VerifyOutcome,
)
from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from mvpose_core.station import StationConfig
from mvpose_core.transforms import RobotConvention
from server.drift import VerifyReport
from server.pipeline import Pipeline
from server.recipes import ActiveRecipe, RecipeBook
from server.state import Services
from server.station import heap
from server.station.camera_view import CameraView
from server.station.handeye import HandEye
from server.station.links import LinkHost
from server.station.measuring import Measuring
from server.station.options import StationOptions
from server.station.queries import StationQueries
from server.station.recorder import Answer, Recorder
from server.station.records import Provenance
from server.station.sink import RecordSink, WriterSink
from server.station.triggers import Triggers
from server.station.verifying import verify_now

log = logging.getLogger(__name__)

__all__ = ["Answer", "RecordSink", "Station", "StationOptions", "WriterSink"]


class Station:
    """One station's hardware, links and pipeline; the links' StationHandler."""

    def __init__(self, station: StationConfig, options: StationOptions | None = None) -> None:
        self.options = options or StationOptions()
        self.measuring = Measuring(station, self.options)
        self.host = LinkHost()
        self.recorder = Recorder(self.options.observer_delay_s, self.measuring.note_append_ms,
                                 lambda: self.host.loop)
        self.triggers = Triggers(self.measuring, self.recorder, self.options,
                                 self._recipe_changed, lambda: self.host.loop)
        self.camera_view = CameraView(self.measuring, lambda: self.triggers.running > 0)
        self.queries: StationQueries | None = None
        self.handeye = HandEye(self)
        self.services: Services | None = None
        self.started_at: datetime | None = None
        # more parts of the status page, by name (e.g. "mqtt": the plant publisher's status)
        self.status_parts: dict[str, Callable[[], dict[str, Any]]] = {
            "camera_view": self.camera_view.status}

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
        assert self.measuring.capture is not None
        log.info("station %s: links %s, cameras %s", self.station.name,
                 {lk.name: lk.status().get("port") for lk in self.links},
                 self.measuring.capture.status())

    def _start(self, services: Services, sink: RecordSink) -> None:
        m = self.measuring
        self.recorder.open(services, sink)
        m.open(services)
        self.triggers.start(services)
        self.queries = StationQueries(services.store, m, self.triggers.between_async,
                                      self._recipe_changed, self.reload_recipes)
        assert m.book is not None and m.provenance is not None
        if m.book.recipes:
            self.recorder.rehearse(m.provenance, m.any_recipe())
        self.recorder.settle(self.options.store_settle_s, self.station.name)
        heap.freeze()  # before the links start: no collection of it ever stalls a trigger
        self.host.start(self.station, self, self.options.answer_margin_s,
                        services.settings.data_dir, {"recipe-versions": self._watch_versions})

    def stop(self) -> None:
        """Stop the links, finish the running trigger and archive writes, close the cameras."""
        self.host.stop()
        self.camera_view.close()
        self.triggers.stop()
        self.recorder.stop_archive()
        self.measuring.close()
        self.recorder.close()
        heap.thaw()

    def run_on_loop(self, coro: Any, timeout: float | None = None) -> Any:
        """Run a coroutine on the station loop from another thread and wait for its result."""
        return self.host.run(coro, timeout)

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        return self.host.loop

    async def _watch_versions(self, period_s: float = 1.0) -> None:
        """Pick up recipe versions activated through the API, between triggers. The store is
        asked on a thread of its own: a trigger never queues behind a frozen database. While
        the line triggers, the question is asked just after a result was answered (in the gap
        before the next trigger, not sharing the GIL with a running one)."""
        heard = asyncio.Event()
        loop, here = asyncio.get_running_loop(), threading.get_ident()

        def answered(_event: ResultEvent) -> None:  # on this loop, unless it had none to use
            if threading.get_ident() == here:
                heard.set()
            else:
                loop.call_soon_threadsafe(heard.set)

        self.add_listener(answered)
        while True:
            await asyncio.sleep(period_s)
            heard.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(heard.wait(), period_s)
            try:
                if not await asyncio.to_thread(self.measuring.versions_changed):
                    continue
                changed = await self.triggers.between_async(self.measuring.reload_versions)
            except RuntimeError:
                return  # the executor is shut down: the station stops
            except Exception:
                log.exception("recipe versions could not be checked")
                continue
            if changed:
                self._recipe_changed()

    def _recipe_changed(self) -> None:
        self.host.recipe_changed()

    # ------------------------------------------------------------------ its rooms' state
    @property
    def station(self) -> StationConfig:
        """The station model under the active calibration."""
        return self.measuring.station

    @property
    def file_station(self) -> StationConfig:
        return self.measuring.file_station

    @property
    def active(self) -> ActiveRecipe | None:
        """The selected recipe."""
        return self.measuring.active

    @property
    def provenance(self) -> Provenance | None:
        """Which station, software and calibration the next record comes from."""
        return self.measuring.provenance

    @property
    def book(self) -> RecipeBook | None:
        return self.measuring.book

    @property
    def pipeline(self) -> Pipeline | None:
        return self.measuring.pipeline

    @property
    def scene(self) -> Any:
        """drivers.cameras.SimScene when the station has simulated cameras."""
        return self.measuring.scene

    @property
    def warmed_ms(self) -> dict[str, float]:
        return self.measuring.warmed_ms

    @property
    def sink(self) -> RecordSink | None:
        return self.recorder.sink

    @property
    def last(self) -> dict[str, Any] | None:
        """The last recorded answer (as the listeners hear of it)."""
        return self.recorder.snapshot()[0]

    @property
    def links(self) -> list[Link]:
        return self.host.links

    def link(self, name: str) -> Link | None:
        """The running link of backend ``name`` (a key of drivers.links.BACKENDS), if any."""
        return self.host.link(name)

    def link_port(self, name: str) -> int:
        """The port the running link of backend ``name`` listens on."""
        link = self.host.link(name)
        port = None if link is None else link.status().get("port")
        if not isinstance(port, int):
            raise RuntimeError(f"the station has no {name} link listening")
        return port

    # ------------------------------------------------------------------ StationHandler (links)
    def measure(self, request: LinkRequest) -> asyncio.Future[LinkOutcome]:
        return self.triggers.measure(request)

    def measure_early(self, request: LinkRequest, answered: Callable[[LinkOutcome], None]
                      ) -> asyncio.Future[LinkOutcome]:
        return self.triggers.measure(request, answered)

    def measure_posted(self, request: LinkRequest, answered: Callable[[LinkOutcome], None]
                       ) -> concurrent.futures.Future[LinkOutcome]:
        out: concurrent.futures.Future[LinkOutcome] = concurrent.futures.Future()
        answer = self.triggers.begin(request, answered)

        def done(f: concurrent.futures.Future[Answer]) -> None:
            if f.cancelled():
                out.cancel()
            elif (err := f.exception()) is not None:
                out.set_exception(err)
            else:
                out.set_result(f.result().outcome)

        answer.add_done_callback(done)
        return out

    def measure_answer(self, request: LinkRequest) -> asyncio.Future[Answer]:
        """:meth:`measure` with the record and the message (the control channel's trigger)."""
        return self.triggers.measure_answer(request)

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        return await self.triggers.record_failure(request, code, message, processing_ms)

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
        await self.triggers.between_async(self.measuring.select, found.config.name, None, "plc")
        self._recipe_changed()  # every link shows it (a PLC handshake: INITIALIZED -> READY)
        return 0

    async def teach_reference(self, by: str) -> int:
        self.measuring.teach_armed_by = by
        return 0

    async def reset(self) -> None:
        await self.triggers.between_async(self.measuring.clear_sequence)

    async def verify(self, link: str, by: str) -> VerifyOutcome:
        return (await self.verify_report(link, by))[0]

    async def verify_report(self, link: str, by: str
                            ) -> tuple[VerifyOutcome, VerifyReport | None, Answer | None]:
        """:meth:`verify` with the report and the trigger's answer (the control channel's)."""
        return await verify_now(self, link, by)

    async def handeye_begin(self, link: str, by: str, holdout: int | None = None
                            ) -> HandEyeOutcome:
        return await self.handeye.begin(link, by, holdout)

    async def handeye_add_pose(self, link: str, by: str, robot_pose: tuple[float, ...] | None
                               ) -> HandEyeOutcome:
        return await self.handeye.add_pose(link, by, robot_pose)

    async def handeye_calculate(self, link: str, by: str) -> HandEyeOutcome:
        return await self.handeye.calculate(link, by)

    async def unselect_recipe(self) -> int:
        return await self._queries().unselect_recipe()

    async def recipes(self) -> list[RecipeInfo]:
        return [] if self.queries is None else await self.queries.recipes()

    async def get_result(self, result_id: int) -> ResultEvent | None:
        return await self._queries().get_result(result_id)

    async def find_results(self, query: ResultQuery) -> tuple[list[ResultEvent], int]:
        return await self._queries().find_results(query)

    async def calibrations(self) -> list[CalibrationInfo]:
        return await self._queries().calibrations()

    async def activate_calibration(self, version: int, by: str) -> tuple[int, str]:
        return await self._queries().activate_calibration(version, by)

    def add_listener(self, listen: Callable[[ResultEvent], None]) -> None:
        """Call ``listen(event)`` after each recorded answer, observer_delay_s after its
        append, on the station loop's thread."""
        self.recorder.add_listener(listen)

    def _queries(self) -> StationQueries:
        if self.queries is None:
            raise RuntimeError("the station is not started")
        return self.queries

    # ------------------------------------------------------------------ control (any thread)
    def trigger(self, part_id: str | None = None, view_index: int = 0,
                trigger_id: int = 0, timeout_s: float = 10.0) -> Answer:
        """A commissioning trigger (control channel): the same thread and record as any link."""
        if self.loop is None or self.active is None:
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
        self.measuring.teach_armed_by = by
        return self.active

    def teach_from_measurement(self, measurement_id: int, by: str) -> ActiveRecipe:
        rec = self.triggers.between(self.measuring.teach_from_measurement, measurement_id, by)
        self._recipe_changed()
        return rec

    def activate_recipe(self, name: str, version: int | None, by: str) -> ActiveRecipe:
        """Select recipe ``name``; with ``version``, activate that stored version first."""
        rec = self.triggers.between(self.measuring.select, name, version, by)
        self._recipe_changed()
        return rec

    def reload_recipes(self) -> bool:
        """Pick up versions activated through the API now (else within a second)."""
        changed = self.triggers.between(self.measuring.reload_versions)
        if changed:
            self._recipe_changed()
        return changed

    def wait_idle(self, timeout_s: float = 10.0) -> None:
        """Block until every trigger, database commit and archive write submitted so far is
        done (tests, demo)."""
        self.triggers.wait_idle(timeout_s)
        self.recorder.wait_idle(timeout_s)

    # ------------------------------------------------------------------ status
    def readiness(self) -> dict[str, bool]:
        capture = self.measuring.capture
        cams = capture.status() if capture else {}
        return {
            "cameras": bool(cams) and all(s.startswith("up") for s in cams.values()),
            "links": self.host.ready(),
            "recipe": self.active is not None,
        }

    def status(self) -> dict[str, Any]:
        m = self.measuring
        active = self.active
        plc = self.host.plc()
        last, counts = self.recorder.snapshot()
        prov = m.provenance
        return {
            "station": self.station.name,
            "state": plc.line_state() if plc is not None else "STOPPED",
            "pid": os.getpid(),
            "started_at": self.started_at.isoformat() if self.started_at else None,
            "deadline_ms": self.station.deadline_ms,
            "recipe": None if active is None else {
                "name": active.config.name, "version": active.version, "number": active.number,
                "sha256": active.sha256, "convention": active.config.robot_convention.value,
            },
            "calibration": None if not prov or not prov.calibration else {
                "id": prov.calibration[0], "sha256": prov.calibration[1],
                "version": m.calibration_version},
            "teach_armed": m.teach_armed_by is not None,
            "cameras": m.capture.status() if m.capture else {},
            "links": self.host.status(),
            "plc": plc.status() if plc is not None else {"running": False},
            "counts": counts,
            "sequence_views": [v.view for v in m.sequence.views] if m.sequence else [],
            "last_result": last,
            "warm_up_ms": {k: round(v, 1) for k, v in m.warmed_ms.items()},
            "store": self.sink.status() if self.sink is not None else None,
            "archive": self.services.images.status() if self.services is not None else None,
            **{name: part() for name, part in self.status_parts.items()},
        }
