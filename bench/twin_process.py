"""The PLC twin in a process of its own, for the station benchmark.

``python -m bench.twin_process PORT PERIOD_MS POLL_MS [SOCKET MOVES_JSON]`` connects to the
station's Modbus/TCP port, resets a watchdog error left by an earlier PLC and then takes blocks
from stdin, one line ``FIRST_ID N`` each: it triggers N times (one every PERIOD_MS, polling every
POLL_MS like a PLC task) and prints one JSON line per block, the roundtrip (trigger written →
RESULT_VALID read) and the processing time the server published, per trigger. With the station's
control socket and a JSON list of offsets (bench/moving_part.py), the part is moved to the next
offset of the cycle before each trigger, as the demo's twin moves it: the line's parts are never
twice at the same place. End of input: it detaches and exits.
A real PLC is another device; running the twin here keeps its client-side Modbus work out of the
server process's CPU and GIL, and one connection serves the whole run, as a PLC's does. For the
same reason the twin runs under the real-time FIFO policy at ``MVPOSE_BENCH_TWIN_PRIORITY``
(default 20, above the station's trigger path; 0: the normal scheduler): a PLC's cycle does not
wait for the station PC's MES load, so neither should the twin's reading of RESULT_VALID.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from drivers.links.layout import Status
from drivers.links.twin import PlcTwin
from server.loopback import attach_twin, detach_twin
from server.station.client import StationClient

ROOT = Path(__file__).resolve().parents[1]  # the child runs as `python -m bench.twin_process`


class TwinProcess:
    """The parent's side of this module: the twin started as a process of its own; blocks of
    handshakes on one connection, one JSON line back per block."""

    def __init__(self, port: int, log: Path, period_ms: float, poll_ms: float,
                 moves: tuple[Path, list[list[float]]] | None = None) -> None:
        self.log = log
        extra = []
        if moves is not None:  # (the station's control socket, the offsets of the cycle)
            moves_file = log.with_suffix(".moves.json")
            moves_file.write_text(json.dumps(moves[1]))
            extra = [str(moves[0]), str(moves_file)]
        with log.open("wb") as err:
            self.proc = subprocess.Popen(  # noqa: S603
                [sys.executable, "-m", "bench.twin_process", str(port), str(period_ms),
                 str(poll_ms), *extra],
                cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err, text=True)
        self._line()  # "ready"

    def _line(self) -> str:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"PLC twin process failed: {self.log.read_text()[-2000:]}")
        return line

    def block(self, first_id: int, n: int) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"{first_id} {n}\n")
        self.proc.stdin.flush()
        return json.loads(self._line())

    def send(self, first_id: int, n: int) -> None:
        """Start a block without waiting for it (the SIGTERM-with-backlog check)."""
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"{first_id} {n}\n")
        self.proc.stdin.flush()

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


class _Moves:
    """The part's cycle of places: the next one before each trigger (a control request)."""

    def __init__(self, socket: str, offsets_file: str) -> None:
        self.client = StationClient(Path(socket), timeout_s=5.0)
        self.offsets: list[list[float]] = json.loads(Path(offsets_file).read_text())
        self.k = 0

    def next(self) -> None:
        self.client.move_part(self.offsets[self.k % len(self.offsets)])
        self.k += 1


async def _block(twin: PlcTwin, first_id: int, n: int, period_s: float,
                 moves: _Moves | None) -> dict:
    rt: list[float] = []
    server: list[float] = []
    nok = 0
    for i in range(n):
        t_next = time.monotonic() + period_s
        if moves is not None:
            moves.next()  # the part is in place before the PLC triggers
        status = await twin.cycle(first_id + i, 0, timeout=5.0)
        rt.append(twin.last_answer_s * 1e3)  # TRIGGER written → RESULT_VALID read
        server.append(status.processing_ms)
        nok += status.result_code != 0 or not status.has(Status.RESULT_VALID)
        await asyncio.sleep(max(0.0, t_next - time.monotonic()))
    return {"roundtrip_ms": rt, "server_ms": server, "nok": nok}


async def _main(port: int, period_s: float, poll_s: float, moves: _Moves | None) -> None:
    twin, beat = await attach_twin(port, poll_s)
    try:
        print("ready", flush=True)
        while line := await asyncio.to_thread(sys.stdin.readline):
            first_id, n = (int(x) for x in line.split())
            print(json.dumps(await _block(twin, first_id, n, period_s, moves)), flush=True)
    finally:
        await detach_twin(twin, beat)


def main(argv: list[str]) -> int:
    port, period_s, poll_s = int(argv[0]), float(argv[1]) / 1000.0, float(argv[2]) / 1000.0
    priority = int(os.environ.get("MVPOSE_BENCH_TWIN_PRIORITY", "20"))
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as err:
            print(f"PLC twin: normal scheduler ({err})", file=sys.stderr, flush=True)
    moves = _Moves(argv[3], argv[4]) if len(argv) > 4 else None
    asyncio.run(_main(port, period_s, poll_s, moves))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
