"""The Modbus/TCP server of the PLC link: pymodbus 3.x inside the caller's asyncio loop.

pymodbus calls the device ``action`` on every register access, before a write is committed: the
action validates, copies the handshake's image into the registers being read, and hands writes to
the handshake runner at once, in the order they come. A TRIGGER write starts its measurement
right there (``StationHandler.measure`` is called before this request's response is sent; see
:class:`~drivers.links.handshake.HandshakeRunner`); only the wait for the outcome runs in a task
of its own. Registers are the fieldbus layout's words (drivers/links/layout.py); the holding
registers 100..169 mirror the input block for PLCs that cannot read input registers.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from ...errors import DriverInitError
from .. import layout as r
from ..base import StationHandler
from ..handshake import Handshake, HandshakeConfig, HandshakeRunner, LinkStats
from ..layout import CONTROL_DEFINED, State
from .transport import ModbusTcpConnection

log = logging.getLogger(__name__)

_WRITE_FCS = frozenset({6, 16, 23})
# Reads: fc 3 and 4, plus the read-back that pymodbus does after a write with fc 6 and fc 23.
_READ_FCS = frozenset({3, 4, 6, 23})


#: Holding registers 100..183 mirror the input registers 0..83 (read-only) for PLCs that cannot
#: read input registers (function code 4).
HR_MIRROR = 100


@dataclass
class PlcStats(LinkStats):
    """Counters of the PLC link (the handshake's and the runner's, plus the transport's)."""

    connections: int = 0
    rejected_connections: int = 0
    rejected_requests: int = 0


class _Listener(ModbusTcpServer):
    """ModbusTcpServer whose connections are checked against the allowlist."""

    def __init__(self, owner: PlcServer, device: SimDevice, host: str, port: int) -> None:
        super().__init__(device, address=(host, port), trace_connect=owner._on_connect)
        self.owner = owner

    def callback_new_connection(self) -> ServerRequestHandler:
        return _Connection(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _Connection(ModbusTcpConnection):
    """One PLC connection: the allowlist, and the map's function codes (docs/modbus.md,
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

    def read_now(self, function_code: int, address: int, count: int) -> list[int] | None:
        # The input block (fc 4) and its holding-register mirror (fc 3) are the handshake's
        # image, which the data store's action would copy in: read it straight from there.
        owner: PlcServer = self.server.owner
        if not owner.runner.started:
            return None
        image = owner.machine.image
        if function_code == 3:
            address -= HR_MIRROR
        if address < 0 or address + count > r.IR_COUNT:
            return None
        return list(image[address : address + count])

    def rejected(self, function_code: int, code: ExcCodes) -> None:
        self.server.owner._reject(code)

    def malformed(self, why: str) -> None:
        self.server.owner.runner.note(f"connection from {self.peer()}: {why}; connection closed")


class PlcServer:
    """The PLC link: Modbus/TCP server + handshake + calls into the measurement pipeline."""

    def __init__(
        self,
        handler: StationHandler,
        config: HandshakeConfig | None = None,
        clock: Callable[[], float] = time.monotonic,
        unit_id: int = 0,
    ) -> None:
        """``unit_id``: the Modbus unit id answered; 0 answers every unit id (a PLC may address
        the server with 0, 1 or 255)."""
        self.handler = handler
        self.config = config or HandshakeConfig()
        self.clock = clock
        self.unit_id = unit_id
        self.stats = PlcStats()
        self.runner = HandshakeRunner(handler, self.config, "modbus", clock, self.stats)
        self._listener: _Listener | None = None

    # ------------------------------------------------------------------ life cycle

    async def start(self, host: str = "127.0.0.1", port: int = 0) -> None:
        """Listen on ``host:port`` (0 = any free port, see ``.port``) and start the handshake."""
        if self._listener is not None:
            raise RuntimeError("PlcServer already started")
        await self.runner.start()
        listener = _Listener(self, self._device(), host, port)
        try:
            await listener.serve_forever(background=True)
        except (OSError, RuntimeError) as err:  # pymodbus: "Could not start listen"
            await listener.shutdown()
            await self.runner.stop()
            raise DriverInitError(
                f"Modbus/TCP address {host}:{port} cannot be listened on (in use, or not an "
                "address of this host)") from err
        self._listener = listener

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
        await self.runner.stop()

    async def __aenter__(self) -> PlcServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    @property
    def machine(self) -> Handshake:
        return self.runner.machine

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
                HR_MIRROR, count=r.IR_COUNT, values=0, datatype=DataType.REGISTERS, readonly=True
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
                lo, hi = max(address, HR_MIRROR), min(address + count, HR_MIRROR + r.IR_COUNT)
                if lo < hi:
                    regs[lo - start : hi - start] = image[lo - HR_MIRROR : hi - HR_MIRROR]
            return None
        if fc not in _WRITE_FCS:
            return self._reject(ExcCodes.ILLEGAL_FUNCTION)
        if address < 0 or address + len(values) > r.HR_WRITABLE_COUNT:
            return self._reject(ExcCodes.ILLEGAL_ADDRESS)
        words = [int(v) for v in values]
        if address == r.HR_CONTROL and words[0] & ~CONTROL_DEFINED:
            return self._reject(ExcCodes.ILLEGAL_VALUE)
        self.runner.write(address, words)
        return None

    def _reject(self, code: ExcCodes) -> ExcCodes:
        self.stats.rejected_requests += 1
        return code

    def _on_connect(self, connected: bool) -> None:
        if connected:
            self.stats.connections += 1

    def recipe_selected(self, number: int, convention_code: int) -> None:
        """The station selected recipe ``number`` by another way than this link (REST, OPC UA)."""
        self.runner.recipe_selected(number, convention_code)
