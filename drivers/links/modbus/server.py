"""The Modbus/TCP server of the PLC link: pymodbus 3.x inside the caller's asyncio loop.

pymodbus calls the device ``action`` on every register access, before a write is committed: the
action validates, copies the handshake's image into the registers being read, and hands writes to
the Handshake at once, in the order they come. A TRIGGER write starts its measurement right there
(``StationHandler.measure`` is called before this request's response is sent; see ``_spawn``);
only the wait for the outcome runs in a task of its own. Requests and outcomes are the seam's
(:class:`~drivers.links.base.LinkRequest`, :class:`~drivers.links.base.LinkOutcome`); the
handshake turns them into registers.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from mvpose_core.reasons import Reason

from ...errors import DriverInitError
from ..base import LinkOutcome, LinkRequest, StationHandler
from . import registers as r
from .machine import Effect, Handshake, HandshakeStats, Measure, ResetPipeline, RunCommand
from .registers import CONTROL_DEFINED, Command, State
from .settings import PlcConfig
from .transport import ModbusTcpConnection

log = logging.getLogger(__name__)

_WRITE_FCS = frozenset({6, 16, 23})
# Reads: fc 3 and 4, plus the read-back that pymodbus does after a write with fc 6 and fc 23.
_READ_FCS = frozenset({3, 4, 6, 23})


@dataclass
class PlcStats:
    """Counters of the PLC link (the handshake's own plus the transport's)."""

    handshake: HandshakeStats
    connections: int = 0
    rejected_connections: int = 0
    rejected_requests: int = 0
    timeouts: int = 0
    handler_errors: int = 0
    writes: int = 0
    last_errors: list[str] = field(default_factory=list)


class _Listener(ModbusTcpServer):
    """ModbusTcpServer whose connections are checked against the allowlist."""

    def __init__(self, owner: PlcServer, device: SimDevice, host: str, port: int) -> None:
        super().__init__(device, address=(host, port), trace_connect=owner._on_connect)
        self.owner = owner

    def callback_new_connection(self) -> ServerRequestHandler:
        return _Connection(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _Connection(ModbusTcpConnection):
    """One PLC connection: the allowlist, and the map's function codes (docs/plc-interface.md,
    "Conformance"); framing, request checks and answer order are ModbusTcpConnection's."""

    function_codes = _WRITE_FCS | {3, 4}

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        peer = transport.get_extra_info("peername")
        host = str(peer[0]) if peer else ""
        owner: PlcServer = self.server.owner
        if not owner.config.allows(host):
            owner.stats.rejected_connections += 1
            log.warning("PLC link: connection from %s refused (not in the allowlist)", host)
            self.close()

    def rejected(self, function_code: int, code: ExcCodes) -> None:
        self.server.owner._reject(code)

    def malformed(self, why: str) -> None:
        self.server.owner._note(f"connection from {self.peer()}: {why}; connection closed")


class PlcServer:
    """The PLC link: Modbus/TCP server + handshake + calls into the measurement pipeline."""

    def __init__(
        self,
        handler: StationHandler,
        config: PlcConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        unit_id: int = 0,
    ) -> None:
        """``unit_id``: the Modbus unit id answered; 0 answers every unit id (a PLC may address
        the server with 0, 1 or 255)."""
        self.handler = handler
        self.config = config or PlcConfig()
        self.clock = clock
        self.unit_id = unit_id
        self._machine: Handshake | None = None
        self._listener: _Listener | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._workers: list[asyncio.Task[None]] = []
        self.stats = PlcStats(HandshakeStats())

    # ------------------------------------------------------------------ life cycle

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> None:
        """Listen on ``host:port`` (0 = any free port, see ``.port``) and start the handshake."""
        if self._listener is not None:
            raise RuntimeError("PlcServer already started")
        machine = Handshake(self.config, self.handler.convention().code, self.clock())
        self._machine = machine
        self.stats.handshake = machine.stats
        if self.config.initial_recipe:
            rc = await self.handler.select_recipe(self.config.initial_recipe)
            if rc == 0:
                machine.set_recipe(self.config.initial_recipe)
                machine.set_convention(self.handler.convention().code)
            else:
                log.warning(
                    "PLC link: initial recipe %d refused (%d)", self.config.initial_recipe, rc
                )
        listener = _Listener(self, self._device(), host, port)
        try:
            await listener.serve_forever(background=True)
        except (OSError, RuntimeError) as err:  # pymodbus: "Could not start listen"
            await listener.shutdown()
            raise DriverInitError(
                f"Modbus/TCP address {host}:{port} cannot be listened on (in use, or not an "
                "address of this host)") from err
        self._listener = listener
        self._workers = [asyncio.create_task(self._ticker(), name="plc-tick")]

    @property
    def port(self) -> int:
        if self._listener is None or self._listener.transport is None:
            raise RuntimeError("PlcServer not started")
        server: asyncio.Server = self._listener.transport  # type: ignore[assignment]
        return int(server.sockets[0].getsockname()[1])

    async def stop(self) -> None:
        """Close every connection, stop the workers and cancel running measurements."""
        if self._listener is not None:
            await self._listener.shutdown()
            self._listener = None
        pending = [*self._workers, *self._tasks]
        for task in pending:
            task.cancel()
        for task in pending:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._workers = []
        self._tasks.clear()

    async def __aenter__(self) -> PlcServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    @property
    def machine(self) -> Handshake:
        if self._machine is None:
            raise RuntimeError("PlcServer not started")
        return self._machine

    @property
    def state(self) -> State:
        return self.machine.state

    def input_registers(self) -> list[int]:
        """A copy of the input-register image (what the PLC reads now)."""
        return list(self.machine.image)

    # ------------------------------------------------------------------ pymodbus side

    def _device(self) -> SimDevice:
        bits = [SimData(0, count=16, values=False, datatype=DataType.BITS)]
        holding = [
            SimData(0, count=r.HR_WRITABLE_COUNT, values=0, datatype=DataType.REGISTERS),
            SimData(
                r.HR_MIRROR, count=r.IR_COUNT, values=0, datatype=DataType.REGISTERS, readonly=True
            ),
        ]
        inputs = [SimData(0, count=r.IR_COUNT, values=0, datatype=DataType.REGISTERS)]
        # id 0: answer every unit id, as a PLC may address us with 0, 1 or 255.
        return SimDevice(self.unit_id, simdata=(bits, list(bits), holding, inputs),
                         action=self._action)

    async def _action(
        self,
        fc: int,
        start: int,
        address: int,
        count: int,
        regs: list[int],
        values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        # Runs before pymodbus commits a write and on every read: no waiting, no slow work.
        if values is None:
            if fc not in _READ_FCS:
                return self._reject(ExcCodes.ILLEGAL_FUNCTION)
            image = self.machine.image
            if fc == 4:
                regs[address - start : address - start + count] = image[address : address + count]
            else:
                lo, hi = max(address, r.HR_MIRROR), min(address + count, r.HR_MIRROR + r.IR_COUNT)
                if lo < hi:
                    regs[lo - start : hi - start] = image[lo - r.HR_MIRROR : hi - r.HR_MIRROR]
            return None
        if fc not in _WRITE_FCS:
            return self._reject(ExcCodes.ILLEGAL_FUNCTION)
        if address < 0 or address + len(values) > r.HR_WRITABLE_COUNT:
            return self._reject(ExcCodes.ILLEGAL_ADDRESS)
        words = [int(v) for v in values]
        if address == r.HR_CONTROL and words[0] & ~CONTROL_DEFINED:
            return self._reject(ExcCodes.ILLEGAL_VALUE)
        self._write(address, words)
        return None

    def _reject(self, code: ExcCodes) -> ExcCodes:
        self.stats.rejected_requests += 1
        return code

    def _on_connect(self, connected: bool) -> None:
        if connected:
            self.stats.connections += 1

    # ------------------------------------------------------------------ workers

    def _write(self, address: int, words: list[int]) -> None:
        # In the action, not in a task fed by a queue: each loop pass between the TRIGGER write
        # and the measurement's start is a chance for another thread of the process (the REST
        # API's) to take the GIL for up to a switch interval (docs/performance.md).
        self.stats.writes += 1
        try:
            effects = self.machine.write(address, words, self.clock())
        except Exception as err:  # noqa: BLE001 — one bad write must not stop the link
            self._note(f"write of {words} at {address} failed: {err!r}")
            return
        for effect in effects:
            self._spawn(effect)

    async def _ticker(self) -> None:
        while True:
            await asyncio.sleep(self.config.tick_s)
            try:
                self.machine.tick(self.clock())
            except Exception as err:  # noqa: BLE001 — keep the heartbeat and watchdog running
                self._note(f"tick failed: {err!r}")

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

    def _note(self, text: str) -> None:
        log.warning("PLC link: %s", text)
        self.stats.last_errors = [*self.stats.last_errors[-9:], text]

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
            self._note(text)
            outcome = await self._failed(req, Reason.TIMEOUT, text, t0)
        except Exception as err:  # noqa: BLE001 — any pipeline failure becomes a result code
            self.stats.handler_errors += 1
            text = f"trigger {req.trigger_id}: measurement raised {err!r}"
            self._note(text)
            outcome = await self._failed(req, Reason.HANDLER_FAILED, text, t0)
        self.machine.measured(outcome)

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
            self._note(f"trigger {req.trigger_id}: recording {code.name} failed: {err!r}")
        return LinkOutcome(int(code), result_id, processing_ms=ms, views_done=0)

    def recipe_selected(self, number: int, convention_code: int) -> None:
        """The station selected recipe ``number`` by another way than this link (REST, OPC UA)."""
        self.machine.set_recipe(number)
        self.machine.set_convention(convention_code)

    async def _command(self, effect: RunCommand) -> None:
        timeout = self.config.command_timeout_s or None
        h = self.handler
        try:
            if effect.command is Command.SELECT_RECIPE:
                result = await asyncio.wait_for(h.select_recipe(effect.argument), timeout)
            elif effect.command is Command.TEACH_REFERENCE:
                result = await asyncio.wait_for(h.teach_reference("plc"), timeout)
            elif effect.command is Command.VERIFY:
                # a measurement: the measure timeout bounds it, as it bounds a trigger
                limit = max(self.config.measure_timeout_s, timeout or 0.0) or None
                verified = await asyncio.wait_for(h.verify("modbus", "plc"), limit)
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
            self._note(f"command {effect.command.name} exceeded {timeout} s")
            result = int(Reason.TIMEOUT)
        except Exception as err:  # noqa: BLE001 — any handler failure becomes a command result
            self.stats.handler_errors += 1
            self._note(f"command {effect.command.name} raised {err!r}")
            result = int(Reason.HANDLER_FAILED)
        self.machine.command_done(effect.command, effect.argument, result)

    async def _reset(self, _effect: ResetPipeline) -> None:
        try:
            await asyncio.wait_for(self.handler.reset(), self.config.command_timeout_s or None)
        except Exception as err:  # noqa: BLE001
            self.stats.handler_errors += 1
            self._note(f"pipeline reset raised {err!r}")
            self.machine.pipeline_reset_failed()
