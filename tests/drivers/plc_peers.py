"""Test peers for the PLC link: a deterministic arithmetic pipeline and server/twin fixtures."""

from __future__ import annotations

import asyncio
import threading
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest_asyncio

from drivers.plc import PlcConfig, PlcServer, TriggerOutcome, TriggerRequest
from drivers.plc.twin import PlcTwin
from mvpose_core.transforms import RobotConvention

NOK_MARKS_MISSING = 7  # a pipeline NOK reason, as the server would define one


def expected_outcome(trigger_id: int) -> TriggerOutcome:
    """The arithmetic pipeline's answer: every value depends on the trigger id, so a stale or
    swapped result block shows up as wrong numbers, not just a wrong id."""
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
    return TriggerOutcome(code, offset, 0.05 + (k % 10) * 0.01, 0.002, 1.0 + (k % 5) * 0.1)


def published_offset(trigger_id: int) -> tuple[float, ...]:
    """The offset the PLC must read for this trigger: zero for a NOK result."""
    want = expected_outcome(trigger_id)
    return want.offset if want.result_code == 0 else (0.0,) * 6


class ArithmeticHandler:
    """A pipeline that does cheap deterministic arithmetic; ``gate`` lets a test hold it busy."""

    def __init__(self) -> None:
        self.gate: asyncio.Event | None = None
        self.fail = False
        self.requests: list[TriggerRequest] = []
        self.resets = 0
        self.teach_requests = 0
        self.conventions = {1: RobotConvention.FANUC, 2: RobotConvention.ABB}
        self.recipe = 0

    async def measure(self, request: TriggerRequest) -> TriggerOutcome:
        self.requests.append(request)
        if self.gate is not None:
            await self.gate.wait()
        if self.fail:
            raise RuntimeError(f"camera timeout on trigger {request.trigger_id}")
        return expected_outcome(request.trigger_id)

    async def select_recipe(self, recipe: int) -> int:
        if recipe not in self.conventions:
            return 3  # pipeline NOK: unknown recipe
        self.recipe = recipe
        return 0

    async def teach_reference(self) -> int:
        self.teach_requests += 1
        return 0

    async def reset(self) -> None:
        self.resets += 1

    def convention_code(self) -> int:
        return self.conventions.get(self.recipe, RobotConvention.FANUC).code


def cfg(**overrides: object) -> PlcConfig:
    """Test settings: recipe 1 selected; a watchdog long enough for a loaded machine's stalls."""
    return PlcConfig(**{"initial_recipe": 1, "watchdog_s": 10.0, **overrides})


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
        config: PlcConfig | None = None,
        connect: bool = True,
        unit_id: int = 0,
        **twin_kw: object,
    ) -> tuple[PlcServer, PlcTwin]:
        server = PlcServer(handler or ArithmeticHandler(), config or cfg(), unit_id=unit_id)
        await server.start()
        servers.append(server)
        order = server.config.word_order
        twin = PlcTwin("127.0.0.1", server.port, word_order=order, **twin_kw)
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
