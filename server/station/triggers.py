"""The trigger path: one thread runs every trigger in order, within its deadline, and answers it.

Threads, and why:

- ``trigger``: one worker runs every trigger (any link, or the control channel) in order, so
  measurements never overlap and the robot-mounted sequence needs no lock; recipe and
  calibration changes run on it too, between triggers;
- ``recorder``: records the answers the station gives without the trigger thread (its watchdog's
  TIMEOUT, a link's own failures), so a stuck trigger thread never stops an answer.

The watchdog answers a trigger that is not recorded within ``deadline + answer_margin_s`` with
a recorded TIMEOUT and makes sure the late result is never recorded: a link and the store never
disagree.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from typing import Any, TypeVar

from drivers.links import LinkOutcome, LinkRequest, relay
from mvpose_core.reasons import Reason
from server.state import Services
from server.station.measuring import Measuring
from server.station.options import StationOptions
from server.station.recorder import Answer, Recorder, tell_early
from server.station.records import failure_record, result_record
from server.station.sequence import Step
from server.store.schemas import ImageRef

log = logging.getLogger(__name__)

T = TypeVar("T")


class _Ticket:
    """One trigger in flight: whoever decides its answer first (the trigger thread recording
    its result, or the watchdog recording TIMEOUT) wins, under the lock."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.state = "running"  # -> "recording" (trigger thread) | "expired" (watchdog)


class Triggers:
    """Runs triggers on the trigger thread and answers each one, recorded, in time."""

    def __init__(self, measuring: Measuring, recorder: Recorder, options: StationOptions,
                 recipe_changed: Callable[[], None],
                 loop_of: Callable[[], asyncio.AbstractEventLoop | None]) -> None:
        self.measuring = measuring
        self.recorder = recorder
        self.options = options
        self._recipe_changed = recipe_changed  # a taught reference: the links show it
        self._loop_of = loop_of  # the station loop: the watchdog's timers run on it
        self.services: Services | None = None
        self.executor: ThreadPoolExecutor | None = None  # the trigger thread
        self._record_exec: ThreadPoolExecutor | None = None
        self.running = 0  # triggers started and not yet done
        self._running_lock = threading.Lock()

    # ------------------------------------------------------------------ life cycle
    def start(self, services: Services) -> None:
        self.services = services
        self.executor = ThreadPoolExecutor(1, thread_name_prefix="trigger")
        self._record_exec = ThreadPoolExecutor(1, thread_name_prefix="recorder")
        for pool in (self.executor, self._record_exec):
            pool.submit(int).result()  # each thread exists before the first trigger needs it

    def stop(self) -> None:
        """Finish the running trigger; drop those not started."""
        for ex in (self.executor, self._record_exec):
            if ex is not None:
                ex.shutdown(wait=True, cancel_futures=True)
        self.executor = self._record_exec = None

    def wait_idle(self, timeout_s: float) -> None:
        """Block until every trigger and recording submitted so far is done."""
        for ex in (self.executor, self._record_exec):
            if ex is not None:
                ex.submit(lambda: None).result(timeout=timeout_s)

    # ------------------------------------------------------------------ between triggers
    def between(self, fn: Callable[..., T], *args: Any) -> T:
        """Run ``fn`` on the trigger thread between triggers and wait for it (any thread but
        the station loop): a recipe never changes under a running measurement."""
        if self.executor is None:
            raise RuntimeError("the station is not running")
        return self.executor.submit(fn, *args).result(timeout=30)

    async def between_async(self, fn: Callable[..., T], *args: Any) -> T:
        """:meth:`between` from a coroutine on the station loop."""
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)

    # ------------------------------------------------------------------ starting a trigger
    def measure(self, request: LinkRequest,
                answered: Callable[[LinkOutcome], None] | None = None
                ) -> asyncio.Future[LinkOutcome]:
        """Start one trigger on the trigger thread now (on the station loop); the future holds
        its outcome, recorded, within the deadline + answer_margin_s. ``answered(outcome)`` is
        called with it on the thread that recorded it, just after the append (before the loop
        hears of it)."""
        out: asyncio.Future[LinkOutcome] = asyncio.get_running_loop().create_future()
        relay(self.measure_answer(request, answered), out, lambda answer: answer.outcome)
        return out

    def measure_answer(self, request: LinkRequest,
                       answered: Callable[[LinkOutcome], None] | None = None
                       ) -> asyncio.Future[Answer]:
        """:meth:`measure` with the record and the message (the control channel's trigger)."""
        return asyncio.wrap_future(self.begin(request, answered))

    def begin(self, request: LinkRequest,
              answered: Callable[[LinkOutcome], None] | None = None
              ) -> concurrent.futures.Future[Answer]:
        """Start one trigger on the trigger thread now, from any thread (the station loop, or a
        link's reader of its process's trigger requests); the future holds its answer,
        recorded, within the deadline + answer_margin_s (the watchdog's timer runs on the
        station loop). ``answered`` as for :meth:`measure`."""
        t0 = time.monotonic()
        at = datetime.now(UTC)
        loop = self._loop_of()
        if self.executor is None or loop is None:
            raise RuntimeError("the station is not running")
        ticket = _Ticket()
        out: concurrent.futures.Future[Answer] = concurrent.futures.Future()
        with self._running_lock:
            self.running += 1
        work = self.executor.submit(self._run, request, t0, at, ticket, answered)
        margin_s = self.options.answer_margin_s
        limit_s = self.measuring.station.deadline_ms / 1000.0 + margin_s

        timer: list[asyncio.TimerHandle] = []  # the watchdog's, once armed (on the loop)

        def done(f: concurrent.futures.Future[Answer | None]) -> None:  # on the trigger thread
            with self._running_lock:
                self.running -= 1
            with ticket.lock:  # a view answered, or a result recorded: nothing to expire
                if ticket.state == "running":
                    ticket.state = "done"
            _settle(out, f)  # None: the watchdog has answered
            # the timer goes now (after the answer), not by waking the loop in a later trigger
            with contextlib.suppress(RuntimeError):  # the loop has closed: the station stops
                loop.call_soon_threadsafe(disarm)

        def expire() -> None:  # on the station loop
            with ticket.lock:
                if ticket.state != "running":
                    return  # answered, or being recorded: the append never takes long
                ticket.state = "expired"
            text = (f"no result within {limit_s * 1e3:.0f} ms (the deadline plus "
                    f"{margin_s * 1e3:.0f} ms): the trigger thread is stuck")
            log.warning("trigger %d: %s", request.trigger_id, text)
            record = self._record_exec
            if record is None:  # the station stopped meanwhile
                out.cancel()
                return
            rec = record.submit(self._record_failure, request, int(Reason.TIMEOUT), text,
                                (time.monotonic() - t0) * 1e3, at, answered)
            rec.add_done_callback(lambda f: _settle(out, f))

        def arm() -> None:  # on the station loop
            if not work.done():
                timer.append(loop.call_later(max(0.0, t0 + limit_s - time.monotonic()),
                                             expire))

        def disarm() -> None:  # on the station loop, after arm
            while timer:
                timer.pop().cancel()

        work.add_done_callback(done)
        try:
            here: asyncio.AbstractEventLoop | None = asyncio.get_running_loop()
        except RuntimeError:
            here = None
        if here is loop:
            arm()
        else:
            loop.call_soon_threadsafe(arm)
        return out

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        """A link's own answer (its backstop timeout, a failed handler), recorded."""
        loop = asyncio.get_running_loop()
        answer = await loop.run_in_executor(self._record_exec, self._record_failure, request,
                                            code, message, processing_ms, datetime.now(UTC))
        return answer.outcome.result_id

    # ------------------------------------------------------------------ the trigger thread
    def _run(self, req: LinkRequest, t0: float, at: datetime, ticket: _Ticket,
             answered: Callable[[LinkOutcome], None] | None = None) -> Answer | None:
        m = self.measuring
        assert m.sequence is not None and m.provenance is not None
        self.recorder.count("triggers")
        try:
            step = m.sequence.run(req, t0)
        except Exception as err:  # a bug: still one answer, recorded
            log.exception("trigger %d failed", req.trigger_id)
            step = None
            refused: tuple[int, str] = (int(Reason.INTERNAL_ERROR),
                                        f"{type(err).__name__}: {err}")
        if step is not None and not step.final:
            self.recorder.count("views")
            view = Answer(LinkOutcome(0, 0, views_done=step.views_done, final=False,
                                      processing_ms=(time.monotonic() - t0) * 1e3),
                          None, "view done")
            tell_early(answered, view.outcome)
            return view
        with ticket.lock:
            if ticket.state == "expired":
                log.warning("trigger %d: its result came after the watchdog's TIMEOUT and is "
                            "not recorded", req.trigger_id)
                return None
            ticket.state = "recording"
        recipe = step.recipe if step is not None else m.any_recipe()
        images: list[ImageRef] = []
        if step is not None and step.result is not None:
            res = step.result
            if self.services is not None:
                images = self.services.images.plan(m.station.name, req.trigger_id, at, res.ok,
                                                   sorted(res.frames))
            record = result_record(m.provenance, res, trigger_id=req.trigger_id,
                                   part_id=req.part_id or None, triggered_at=at, recipe=recipe,
                                   images=images)
            message = res.message
        else:
            code, message = step.refused if step is not None and step.refused else refused
            record = failure_record(m.provenance, code=code, message=message,
                                    trigger_id=req.trigger_id, part_id=req.part_id or None,
                                    triggered_at=at, recipe=recipe,
                                    total_ms=(time.monotonic() - t0) * 1e3)
        answer = self.recorder.append(record, message, t0, req.link, answered)
        archiving = False
        if step is not None and step.result is not None and answer.record is not None:
            archiving = self._after(step, answer)
        if images and not archiving and self.services is not None:
            self.services.images.release()  # the record was not stored: no frames to write
        return answer

    def _record_failure(self, req: LinkRequest, code: int, message: str, total_ms: float,
                        at: datetime, answered: Callable[[LinkOutcome], None] | None = None
                        ) -> Answer:
        m = self.measuring
        assert m.provenance is not None
        m.clear_sequence()  # a failed trigger ends any multi-view sequence
        record = failure_record(m.provenance, code=code, message=message,
                                trigger_id=req.trigger_id, part_id=req.part_id or None,
                                triggered_at=at, recipe=m.any_recipe(), total_ms=total_ms)
        return self.recorder.append(record, message, time.monotonic() - total_ms / 1e3,
                                    req.link, answered)

    def _after(self, step: Step, answer: Answer) -> bool:
        """Teach if armed; hand the record's planned frames to the archive (True if it has)."""
        rec = answer.record
        assert rec is not None and step.result is not None
        if self.measuring.teach_if_armed(step.recipe, rec, answer.outcome.result_id):
            self._recipe_changed()
        return self.recorder.archive(answer, step.result.frames)



def _settle(out: concurrent.futures.Future[Answer],
            src: concurrent.futures.Future[Answer | None] | concurrent.futures.Future[Answer]
            ) -> None:
    """End ``out`` as ``src`` ended (a result of None leaves it to the watchdog's record),
    unless it has ended already."""
    try:
        if src.cancelled():
            out.cancel()
        elif (err := src.exception()) is not None:
            out.set_exception(err)
        elif (answer := src.result()) is not None:
            out.set_result(answer)
    except concurrent.futures.InvalidStateError:
        pass  # the other side (trigger thread or watchdog) decided first
