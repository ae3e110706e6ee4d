"""The handshake at work: runs the machine's effects against the station, whatever the bus.

A backend owns the wire (Modbus registers, an EtherNet/IP assembly, an S7 data block, a
PROFINET submodule) and hands the runner what the PLC wrote (:meth:`HandshakeRunner.write` at a
word address, or a whole output image with :meth:`HandshakeRunner.write_output`); it sends the
PLC :meth:`HandshakeRunner.input_image` (or the machine's words). The runner calls the
:class:`~drivers.links.base.StationHandler` (measure, commands, verify, reset) with the link's
timeouts, turns every failure into a result or command code, and ticks the heartbeat and the
watchdog. Everything runs in the caller's asyncio loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from mvpose_core.calibration.codes import HandEyeCode
from mvpose_core.reasons import Reason

from ..base import HandEyeOutcome, LinkOutcome, LinkRequest, StationHandler
from ..layout import INPUT, OUTPUT, ByteOrder, Command
from .config import HandshakeConfig
from .machine import Effect, Handshake, HandshakeStats, Measure, ResetPipeline, RunCommand

log = logging.getLogger(__name__)

_HANDEYE = (Command.HANDEYE_BEGIN, Command.HANDEYE_ADD_POSE, Command.HANDEYE_CALCULATE)
#: the longest a hand-eye calculate may take (a solve and its leave-one-out report)
CALCULATE_S = 300.0


@dataclass
class LinkStats:
    """Counters of a handshake link: the machine's own plus the runner's."""

    handshake: HandshakeStats = field(default_factory=HandshakeStats)
    timeouts: int = 0
    handler_errors: int = 0
    writes: int = 0
    last_errors: list[str] = field(default_factory=list)


class HandshakeRunner:
    """The handshake machine plus the calls into the station it asks for."""

    def __init__(
        self,
        handler: StationHandler,
        config: HandshakeConfig | None = None,
        link: str = "modbus",
        clock: Callable[[], float] = time.monotonic,
        stats: LinkStats | None = None,
    ) -> None:
        self.handler = handler
        self.config = config or HandshakeConfig()
        self.link = link
        self.clock = clock
        self.stats = stats if stats is not None else LinkStats()
        self._machine: Handshake | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._ticker: asyncio.Task[None] | None = None
        self._last_output: bytes | None = None
        #: called whenever the machine's image may have changed (a cyclic backend sends its
        #: input image then, instead of polling for it)
        self.on_change: Callable[[], None] | None = None

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        """Build the machine, select the initial recipe and start the heartbeat/watch ticks."""
        if self._machine is not None:
            raise RuntimeError(f"the {self.link} handshake is already started")
        machine = Handshake(self.config, self.handler.convention().code, self.clock(), self.link)
        self._machine = machine
        self.stats.handshake = machine.stats
        if self.config.initial_recipe:
            rc = await self.handler.select_recipe(self.config.initial_recipe)
            if rc == 0:
                machine.set_recipe(self.config.initial_recipe)
                machine.set_convention(self.handler.convention().code)
            else:
                log.warning("%s link: initial recipe %d refused (%d)", self.link,
                            self.config.initial_recipe, rc)
        self._ticker = asyncio.create_task(self._tick(), name=f"{self.link}-tick")

    async def stop(self) -> None:
        """Stop the ticks and cancel running measurements and commands."""
        pending = [*([self._ticker] if self._ticker else []), *self._tasks]
        for task in pending:
            task.cancel()
        for task in pending:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._ticker = None
        self._tasks.clear()

    @property
    def machine(self) -> Handshake:
        if self._machine is None:
            raise RuntimeError(f"the {self.link} handshake is not started")
        return self._machine

    @property
    def started(self) -> bool:
        return self._machine is not None

    # ------------------------------------------------------------------ the PLC's side

    def write(self, address: int, words: list[int]) -> None:
        """The PLC wrote ``words`` at word ``address`` of the output block (already checked).

        Effects start here, not in a task fed by a queue: each loop pass between the TRIGGER
        write and the measurement's start is a chance for another thread of the process (the
        REST API's) to take the GIL for up to a switch interval (docs/performance.md).
        """
        self.stats.writes += 1
        try:
            effects = self.machine.write(address, words, self.clock())
        except Exception as err:  # noqa: BLE001 — one bad write must not stop the link
            self.note(f"write of {words} at {address} failed: {err!r}")
            return
        for effect in effects:
            self._spawn(effect)
        self._changed()

    def write_output(self, data: bytes, order: ByteOrder) -> None:
        """A whole output image from a cyclic bus. Call it with every image received: an
        unchanged image costs a comparison; the machine finds the edges in a changed one."""
        if data == self._last_output:
            return
        if len(data) != OUTPUT.size:
            raise ValueError(f"the output block is {OUTPUT.size} bytes, got {len(data)}")
        words = OUTPUT.to_words(data, order)
        self._last_output = bytes(data)
        self.write(0, words)

    def input_image(self, order: ByteOrder) -> bytes:
        """The input block as the PLC reads it now, in the bus's byte order."""
        return INPUT.to_bytes(self.machine.image, order)

    def recipe_selected(self, number: int, convention_code: int) -> None:
        """The station selected recipe ``number`` by another way than this link."""
        self.machine.set_recipe(number)
        self.machine.set_convention(convention_code)
        self._changed()

    def _changed(self) -> None:
        if self.on_change is not None:
            try:
                self.on_change()
            except Exception as err:  # noqa: BLE001 — the backend's problem, not the machine's
                self.note(f"on_change failed: {err!r}")

    def note(self, text: str) -> None:
        """Log a link problem and keep the last ten for the link's status."""
        log.warning("%s link: %s", self.link, text)
        self.stats.last_errors = [*self.stats.last_errors[-9:], text]

    # ------------------------------------------------------------------ effects

    async def _tick(self) -> None:
        while True:
            await asyncio.sleep(self.config.tick_s)
            try:
                self.machine.tick(self.clock())
            except Exception as err:  # noqa: BLE001 — keep the heartbeat and watchdog running
                self.note(f"tick failed: {err!r}")
            self._changed()

    def _spawn(self, effect: Effect) -> None:
        if isinstance(effect, Measure):
            # measure() is called here, not in the task: a handler that starts its work when
            # called (the station runtime does) starts it before the task's first step.
            pending: Awaitable[LinkOutcome] | Exception
            if effect.refused is not None:
                pending = ValueError(effect.refused)
            else:
                try:
                    pending = self.handler.measure(effect.request)
                except Exception as err:  # noqa: BLE001 — reported as the measurement's failure
                    pending = err
            coro = self._measure(effect, pending, self.clock())
        elif isinstance(effect, RunCommand):
            coro = self._command(effect)
        else:
            coro = self._reset(effect)
        task = asyncio.create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _measure(
        self, effect: Measure, pending: Awaitable[LinkOutcome] | Exception, t0: float
    ) -> None:
        req = effect.request
        timeout = self.config.measure_timeout_s or None
        try:
            if isinstance(pending, Exception):
                raise pending
            # asyncio.timeout awaits the handler in this task; wait_for would wrap it in another
            # one, a loop pass more between the work's end and the outcome's publication.
            async with asyncio.timeout(timeout):
                outcome = await pending
            if not isinstance(outcome, LinkOutcome):
                raise TypeError(f"measure() returned {type(outcome).__name__}, not LinkOutcome")
        except TimeoutError:
            self.stats.timeouts += 1
            text = f"trigger {req.trigger_id}: measurement exceeded {timeout} s"
            self.note(text)
            outcome = await self._failed(req, Reason.TIMEOUT, text, t0)
        except Exception as err:  # noqa: BLE001 — any pipeline failure becomes a result code
            self.stats.handler_errors += 1
            text = f"trigger {req.trigger_id}: measurement raised {err!r}"
            self.note(text)
            outcome = await self._failed(req, Reason.HANDLER_FAILED, text, t0)
        self.machine.measured(outcome)
        self._changed()

    async def _failed(self, req: LinkRequest, code: Reason, text: str,
                      t0: float) -> LinkOutcome:
        # A failed trigger ends any multi-view sequence, so the pipeline must forget its views.
        await self._reset(ResetPipeline())
        ms = (self.clock() - t0) * 1e3
        result_id = 0
        try:  # the answer gets a record of its own, with the same code
            async with asyncio.timeout(self.config.command_timeout_s or None):
                result_id = int(await self.handler.record_failure(req, int(code), text, ms))
        except Exception as err:  # noqa: BLE001 — the PLC still gets its answer
            self.note(f"trigger {req.trigger_id}: recording {code.name} failed: {err!r}")
        return LinkOutcome(int(code), result_id, processing_ms=ms, views_done=0)

    async def _command(self, effect: RunCommand) -> None:
        timeout = self.config.command_timeout_s or None
        h = self.handler
        try:
            if effect.command is Command.SELECT_RECIPE:
                result = await asyncio.wait_for(h.select_recipe(effect.argument), timeout)
            elif effect.command is Command.TEACH_REFERENCE:
                result = await asyncio.wait_for(h.teach_reference("plc"), timeout)
            elif effect.command in _HANDEYE:
                result = await self._handeye(effect, timeout)
            elif effect.command is Command.VERIFY:
                # a measurement: the measure timeout bounds it, as it bounds a trigger
                limit = max(self.config.measure_timeout_s, timeout or 0.0) or None
                verified = await asyncio.wait_for(h.verify(self.link, "plc"), limit)
                self.machine.verified(verified)
                result = verified.result_code
            else:
                await asyncio.wait_for(h.reset(), timeout)
                result = 0
            if not isinstance(result, int):
                raise TypeError(f"{effect.command.name} returned {result!r}, not an int")
            if result == 0 and effect.command is Command.SELECT_RECIPE:
                self.machine.set_convention(h.convention().code)
        except TimeoutError:
            self.stats.timeouts += 1
            self.note(f"command {effect.command.name} exceeded {timeout} s")
            result = int(Reason.TIMEOUT)
        except Exception as err:  # noqa: BLE001 — any handler failure becomes a command result
            self.stats.handler_errors += 1
            self.note(f"command {effect.command.name} raised {err!r}")
            result = int(Reason.HANDLER_FAILED)
        self.machine.command_done(effect.command, effect.argument, result)
        self._changed()

    async def _handeye(self, effect: RunCommand, timeout: float | None) -> int:
        """A hand-eye step: its block, then its code as the command result."""
        h = self.handler
        if effect.command is Command.HANDEYE_BEGIN:
            call = h.handeye_begin(self.link, "plc", effect.argument or None)
        elif effect.command is Command.HANDEYE_ADD_POSE:
            if effect.refused is not None:  # not a pose: refused as the session would
                self.note(f"HANDEYE_ADD_POSE: {effect.refused}")
                outcome = HandEyeOutcome(int(HandEyeCode.BAD_POSE), message=effect.refused)
                self.machine.handeye_done(outcome)
                return outcome.code
            # a capture and a detection: the measure timeout bounds it, as it bounds a trigger
            timeout = max(self.config.measure_timeout_s, timeout or 0.0) or None
            call = h.handeye_add_pose(self.link, "plc", effect.robot_pose)
        else:  # a solve and its report: minutes at most
            timeout = max(CALCULATE_S, timeout or 0.0)
            call = h.handeye_calculate(self.link, "plc")
        outcome = await asyncio.wait_for(call, timeout)
        self.machine.handeye_done(outcome)
        return outcome.code

    async def _reset(self, _effect: ResetPipeline) -> None:
        try:
            await asyncio.wait_for(self.handler.reset(), self.config.command_timeout_s or None)
        except Exception as err:  # noqa: BLE001
            self.stats.handler_errors += 1
            self.note(f"pipeline reset raised {err!r}")
            self.machine.pipeline_reset_failed()
            self._changed()
