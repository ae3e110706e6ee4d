"""Test peers for the PLC link: a deterministic arithmetic pipeline and server/twin fixtures."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest_asyncio

from drivers.links.base import LinkOutcome, LinkRequest
from drivers.links.modbus import HandshakeConfig, PlcServer
from drivers.links.modbus.twin import modbus_twin
from drivers.links.twin import PlcTwin
from mvpose_core.transforms import RobotConvention

NOK_MARKS_MISSING = 7  # a pipeline NOK reason, as the server would define one


def expected_outcome(trigger_id: int, result_id: int = 0) -> LinkOutcome:
    """The arithmetic pipeline's answer: every value depends on the trigger id, so a stale or
    swapped result block shows up as wrong numbers, not just a wrong id. The offset is in the
    FANUC convention (6 values, the PLC form as it is)."""
    k = trigger_id
    offset = (
        (k % 1000) * 0.001 + 0.5,
        -(k % 777) * 0.01,
        1.25 + (k % 3),
        (k % 360) * 0.01 - 1.8,
        ((k * 7) % 1000) * 1e-4,
        -179.5 + (k % 50),
    )
    code = NOK_MARKS_MISSING if k % 13 == 0 else 0
    return LinkOutcome(code, result_id, offset if code == 0 else None,
                       0.05 + (k % 10) * 0.01, 0.002, 1.0 + (k % 5) * 0.1)


def published_offset(trigger_id: int) -> tuple[float, ...]:
    """The offset the PLC must read for this trigger: zero for a NOK result."""
    want = expected_outcome(trigger_id)
    return want.offset if want.offset is not None else (0.0,) * 6


class ArithmeticHandler:
    """The station side of the link as a StationHandler that does cheap deterministic
    arithmetic and numbers its answers as a store does (``seq``); ``gate`` lets a test hold it
    busy. Only the calls the Modbus backend makes are here."""

    def __init__(self) -> None:
        self.gate: asyncio.Event | None = None
        self.fail = False
        self.requests: list[LinkRequest] = []
        self.failures: list[tuple[int, int, str]] = []
        self.resets = 0
        self.teach_requests = 0
        self.conventions = {1: RobotConvention.FANUC, 2: RobotConvention.ABB}
        self.recipe = 0
        self.seq = 0  # the last result id given

    def next_id(self) -> int:
        self.seq += 1
        return self.seq

    async def measure(self, request: LinkRequest) -> LinkOutcome:
        self.requests.append(request)
        if self.gate is not None:
            await self.gate.wait()
        if self.fail:
            raise RuntimeError(f"camera timeout on trigger {request.trigger_id}")
        return expected_outcome(request.trigger_id, self.next_id())

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        self.failures.append((request.trigger_id, code, message))
        return self.next_id()

    async def select_recipe(self, number: int) -> int:
        if number not in self.conventions:
            return 3  # pipeline NOK: unknown recipe
        self.recipe = number
        return 0

    async def teach_reference(self, by: str) -> int:
        self.teach_requests += 1
        return 0

    async def reset(self) -> None:
        self.resets += 1

    def convention(self) -> RobotConvention:
        return self.conventions.get(self.recipe, RobotConvention.FANUC)

    def selected_recipe(self) -> int:
        return self.recipe


def cfg(**overrides: object) -> HandshakeConfig:
    """Test settings: recipe 1 selected; a watchdog long enough for a loaded machine's stalls."""
    return HandshakeConfig(**{"initial_recipe": 1, "watchdog_s": 10.0, **overrides})


ServerFactory = Callable[..., Awaitable[tuple[PlcServer, PlcTwin]]]


@pytest_asyncio.fixture
async def plc() -> AsyncIterator[ServerFactory]:
    """Start a PlcServer on a free loopback port plus a connected, enabled twin; stop both after
    the test and fail if a task or thread is left behind."""
    threads_before = set(threading.enumerate())
    servers: list[PlcServer] = []
    twins: list[PlcTwin] = []

    async def make(
        handler: object | None = None,
        config: HandshakeConfig | None = None,
        connect: bool = True,
        unit_id: int = 0,
        **twin_kw: object,
    ) -> tuple[PlcServer, PlcTwin]:
        server = PlcServer(handler or ArithmeticHandler(),  # type: ignore[arg-type]
                           config or cfg(), unit_id=unit_id)
        await server.start()
        servers.append(server)
        order = server.config.word_order
        twin = modbus_twin("127.0.0.1", server.port, word_order=order, **twin_kw)
        if connect:
            await twin.connect()
            twins.append(twin)
            await twin.enable()
        return server, twin

    yield make
    for twin in twins:
        twin.close()
    for server in servers:
        await server.stop()
    # Let closed transports run their callbacks before counting what is left.
    for _ in range(3):
        await asyncio.sleep(0)
    current = asyncio.current_task()
    leaked = [t for t in asyncio.all_tasks() if t is not current and not t.done()]
    assert not leaked, f"tasks left running: {leaked}"
    # asyncio's default executor (asyncio.to_thread) keeps its workers until the loop closes.
    extra = {
        t for t in set(threading.enumerate()) - threads_before if not t.name.startswith("asyncio_")
    }
    assert not extra, f"threads left running: {extra}"
