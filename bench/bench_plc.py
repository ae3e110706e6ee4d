"""PLC link benchmark: the handshake's own cost on loopback (trigger written → result valid seen by
the PLC twin, with an instant pipeline; target p99 ≤ 2 ms), next to a bare register read."""

from __future__ import annotations

import asyncio
import gc
import time
from collections.abc import Callable

import numpy as np

from bench.timing import Timing, check
from drivers.links.base import LinkOutcome, LinkRequest
from drivers.links.modbus import Control, HandshakeConfig, PlcServer, Status
from drivers.links.modbus.twin import modbus_twin
from drivers.links.twin import PlcStatus
from mvpose_core.transforms import RobotConvention

HANDSHAKE_P99_TARGET_MS = 2.0
N = 2000


class InstantPipeline:
    """Answers at once, so the numbers are the PLC link's own cost (the calls of
    drivers.links.base.StationHandler that the Modbus backend makes)."""

    def __init__(self) -> None:
        self.seq = 0

    async def measure(self, request: LinkRequest) -> LinkOutcome:
        self.seq += 1
        return LinkOutcome(0, self.seq, (1.0, 2.0, 3.0, 0.1, 0.2, 0.3), 0.05, 0.01, 0.0)

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        self.seq += 1
        return self.seq

    async def select_recipe(self, recipe: int) -> int:
        return 0

    async def teach_reference(self, by: str) -> int:
        return 0

    async def reset(self) -> None:
        return None

    def convention(self) -> RobotConvention:
        return RobotConvention.FANUC


def _toggled(before: bool) -> Callable[[PlcStatus], bool]:
    return lambda s: s.has(Status.DONE_TOGGLE) != before


async def _run() -> tuple[Timing, Timing, Timing]:
    server = PlcServer(InstantPipeline(),  # type: ignore[arg-type]
                       HandshakeConfig(initial_recipe=1, watchdog_s=0))
    await server.start()
    twin = modbus_twin("127.0.0.1", server.port)
    await twin.connect()
    try:
        await twin.enable()
        reads = np.empty(N)
        for i in range(N):
            t0 = time.perf_counter()
            await twin.read_status()
            reads[i] = (time.perf_counter() - t0) * 1e3
        handshake = np.empty(N)
        cycle = np.empty(N)
        for i in range(N):
            ready = await twin.wait_for(lambda s: s.has(Status.READY), what="READY")
            toggle = ready.has(Status.DONE_TOGGLE)
            t0 = time.perf_counter()
            await twin.write_trigger(i + 1)
            answer = await twin.wait_for(_toggled(toggle), what="result")
            t1 = time.perf_counter()
            if answer.trigger_id != i + 1 or answer.result_id != i + 1:
                raise RuntimeError(f"handshake {i + 1}: got result {answer.result_id}")
            await twin.set_control(Control.TRIGGER_ENABLE | Control.RESULT_ACK)
            await twin.wait_for(lambda s: not s.has(Status.RESULT_VALID), what="ack")
            handshake[i] = (t1 - t0) * 1e3
            cycle[i] = (time.perf_counter() - t0) * 1e3
    finally:
        twin.close()
        await server.stop()
    return (
        Timing("Modbus read of the 50-register status block", reads),
        Timing("handshake: trigger written -> result valid", handshake),
        Timing("full cycle: trigger -> result -> ack -> ready", cycle),
    )


def main() -> int:
    gc_was = gc.isenabled()
    gc.disable()
    try:
        read, handshake, cycle = asyncio.run(_run())
    finally:
        if gc_was:
            gc.enable()
    print(read.line())
    print(handshake.line(read))
    print(cycle.line(read))
    ok = check("handshake p99", handshake.p99, HANDSHAKE_P99_TARGET_MS)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
