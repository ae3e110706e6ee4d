"""The record of every answer: made durable first, then counted, kept as the last result, told to
the listeners and its frames archived.

Every answer the station gives goes through :meth:`Recorder.append`: the record is appended to
the sink (its seq is the result id the link publishes), then the link's outcome is built from
the same record. Threads: ``archive`` writes archived frames as PNG once the database has the
record, after the link has its answer, niced (server.station.scheduling.background).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from drivers.links import LinkOutcome
from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from server.recipes import ActiveRecipe
from server.state import Services
from server.station import scheduling
from server.station.records import Provenance, failure_record
from server.station.sink import RecordSink
from server.store.events import record_event
from server.store.schemas import MeasurementRecord

log = logging.getLogger(__name__)


@dataclass
class Answer:
    """One trigger's answer as the station gave it, with its record."""

    outcome: LinkOutcome
    record: MeasurementRecord | None
    message: str
    db_id: int | None = None
    on_committed: Callable[[Callable[[int], object]], None] | None = None
    event: ResultEvent | None = None  # the recorded answer's event (None: not recorded)


class Recorder:
    """Appends the station's records; keeps the counts and the last result; tells listeners."""

    def __init__(self, observer_delay_s: float, note_append_ms: Callable[[float], None],
                 loop_of: Callable[[], asyncio.AbstractEventLoop | None]) -> None:
        self.observer_delay_s = observer_delay_s
        self._note_append_ms = note_append_ms  # the pipeline's deadline reserve
        self._loop_of = loop_of  # the station loop, on which listeners are called
        self.sink: RecordSink | None = None
        self.services: Services | None = None
        self.counts: dict[str, int] = {"triggers": 0, "ok": 0, "nok": 0, "views": 0,
                                       "store_failed": 0}
        self.last: dict[str, Any] | None = None
        self.store_error: str | None = None  # the last append that failed, why
        self._lock = threading.Lock()  # last result and counts, read by the control channel
        self._listeners: list[Callable[[ResultEvent], None]] = []
        self._archive_exec: ThreadPoolExecutor | None = None

    # ------------------------------------------------------------------ life cycle
    def open(self, services: Services, sink: RecordSink) -> None:
        self.services = services
        self.sink = sink
        self._archive_exec = ThreadPoolExecutor(1, thread_name_prefix="archive",
                                                initializer=scheduling.background)
        self._archive_exec.submit(int).result()  # the thread exists before the first record

    def rehearse(self, prov: Provenance, recipe: ActiveRecipe) -> None:
        """Records built and sealed as an append does, nothing kept (the first real append
        then finds its code warm)."""
        assert self.sink is not None
        for _ in range(8):
            self.sink.rehearse(failure_record(
                prov, code=int(Reason.INTERNAL_ERROR), message="rehearsal", trigger_id=0,
                part_id=None, triggered_at=datetime.now(UTC), recipe=recipe, total_ms=0.0))

    def settle(self, settle_s: float, station: str) -> None:
        """Wait up to ``settle_s`` for the journal's zeros ahead: the first appends then share
        the disk with no zero piece being written."""
        assert self.sink is not None
        if not self.sink.settle(settle_s):
            log.warning("station %s: the store's journal has not written its space ahead "
                        "within %.1f s; the first appends grow the file", station, settle_s)

    def stop_archive(self) -> None:
        if self._archive_exec is not None:
            self._archive_exec.shutdown(wait=True, cancel_futures=True)
        self._archive_exec = None

    def close(self) -> None:
        self.stop_archive()
        if self.sink is not None:
            self.sink.close()  # what the database did not take yet stays in the journal
            self.sink = None

    def wait_idle(self, timeout_s: float) -> None:
        """Block until every database commit and archive write submitted so far is done."""
        flush = getattr(self.sink, "flush", None)
        if flush is not None:
            flush(timeout_s)
        if self._archive_exec is not None:
            self._archive_exec.submit(lambda: None).result(timeout=timeout_s)

    # ------------------------------------------------------------------ counts
    def count(self, name: str) -> None:
        with self._lock:
            self.counts[name] += 1

    def snapshot(self) -> tuple[dict[str, Any] | None, dict[str, int]]:
        """(the last result, the counts), copied under the lock."""
        with self._lock:
            return (None if self.last is None else dict(self.last)), dict(self.counts)

    # ------------------------------------------------------------------ appends
    def append(self, record: MeasurementRecord, message: str, t0: float,
               link: str = "", answered: Callable[[LinkOutcome], None] | None = None) -> Answer:
        """Make ``record`` durable, then build the link's outcome from it (the same code);
        ``answered(outcome)`` is called with it at once, on this thread, before anything else
        here wakes another thread (a link in a process of its own posts it to its child)."""
        assert self.sink is not None
        t = time.monotonic()
        try:
            done = self.sink.append(record)
        except Exception as err:
            log.exception("trigger %d: the record could not be stored", record.trigger_id)
            with self._lock:  # the alarm watch (server.station.alarms) raises STORE_FAILED
                self.counts["store_failed"] += 1
                self.store_error = f"{type(err).__name__}: {str(err)[:200]}"
            code = int(Reason.STORE_FAILED)
            failed = LinkOutcome(code, 0, processing_ms=(time.monotonic() - t0) * 1e3)
            tell_early(answered, failed)
            return Answer(failed, None, f"the record could not be stored: {err}")
        self._note_append_ms((time.monotonic() - t) * 1e3)
        event = record_event(record, done.result_id)
        outcome = LinkOutcome.from_event(event, processing_ms=(time.monotonic() - t0) * 1e3)
        tell_early(answered, outcome)
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

    def _committed(self, result_id: int, db_id: int) -> None:
        with self._lock:
            if self.last is not None and self.last["result_id"] == result_id:
                self.last["measurement_id"] = db_id

    # ------------------------------------------------------------------ listeners
    def add_listener(self, listen: Callable[[ResultEvent], None]) -> None:
        """Call ``listen(event)`` after each recorded answer, observer_delay_s after its
        append, on the station loop's thread."""
        self._listeners.append(listen)

    def _tell_later(self, event: ResultEvent) -> None:
        """Call the listeners with ``event`` observer_delay_s from now, on the station loop (at
        once on this thread when there is no loop to wait on)."""
        loop, delay = self._loop_of(), self.observer_delay_s
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

    # ------------------------------------------------------------------ the archive
    def archive(self, answer: Answer, frames: Mapping[tuple[int, str], np.ndarray]) -> bool:
        """Hand the record's planned frames to the archive (True if it has them)."""
        rec = answer.record
        archive = self._archive_exec
        if rec is None or not rec.images or archive is None or answer.on_committed is None:
            return False
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

    def _archive(self, measurement_id: int, rec: MeasurementRecord,
                 frames: Mapping[tuple[int, str], np.ndarray]) -> None:
        assert self.services is not None
        try:
            self.services.images.write(measurement_id, rec.images, rec.result == "OK", frames)
        except Exception:
            log.exception("measurement %d: archiving its frames failed", measurement_id)


def tell_early(answered: Callable[[LinkOutcome], None] | None, outcome: LinkOutcome) -> None:
    """Call ``answered(outcome)``, if given; a failure is logged (the answer still goes out
    through the link's loop)."""
    if answered is None:
        return
    try:
        answered(outcome)
    except Exception:
        log.exception("telling a link its answer early failed")
