"""The PLC twin in a process of its own, for the station benchmark: one phase of handshakes.

``python -m bench.twin_process PORT FIRST_ID N PERIOD_MS POLL_MS`` connects to the station's
Modbus/TCP port, resets a watchdog error left by an earlier PLC, triggers N times (one every
PERIOD_MS, polling every POLL_MS like a PLC task) and prints one JSON line: the roundtrip
(trigger written → RESULT_VALID read) and the processing time the server published, per trigger.
A real PLC is another device; running the twin here keeps its client-side Modbus work out of the
server process's CPU and GIL.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time

from drivers.plc.registers import Status
from server.loopback import attach_twin, detach_twin


async def _phase(port: int, first_id: int, n: int, period_s: float, poll_s: float) -> dict:
    twin, beat = await attach_twin(port, poll_s)
    rt: list[float] = []
    server: list[float] = []
    nok = 0
    try:
        for i in range(n):
            t_next = time.monotonic() + period_s
            status = await twin.cycle(first_id + i, 0, timeout=5.0)
            rt.append(twin.last_answer_s * 1e3)  # TRIGGER written → RESULT_VALID read
            server.append(status.processing_ms)
            nok += status.result_code != 0 or not status.has(Status.RESULT_VALID)
            await asyncio.sleep(max(0.0, t_next - time.monotonic()))
    finally:
        await detach_twin(twin, beat)
    return {"roundtrip_ms": rt, "server_ms": server, "nok": nok}


def main(argv: list[str]) -> int:
    port, first_id, n = int(argv[0]), int(argv[1]), int(argv[2])
    period_s, poll_s = float(argv[3]) / 1000.0, float(argv[4]) / 1000.0
    print(json.dumps(asyncio.run(_phase(port, first_id, n, period_s, poll_s))), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
