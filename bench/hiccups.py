"""The platform's own stalls: how late a real-time thread wakes on each core (a hiccup meter).

``python -m bench.hiccups [SECONDS [THRESHOLD_MS]]`` runs one process per core, pinned to it,
under SCHED_FIFO 50 (above the station's trigger path and the bench's PLC twin), each sleeping
5 ms at a time and printing every wake-up later than THRESHOLD_MS (default 3) past its time as
one line ``CORE WALL_TIME MS_LATE`` (the wall-clock time the stall began), until SECONDS have
passed (default: until it is terminated). Nothing of the station runs at that priority, so a
late wake-up here is time the core gave to no task of this machine (the hypervisor ran
something else, or the kernel did): a trigger slowed at the same moment was slowed by the
platform, not by the station. ``MVPOSE_BENCH_HICCUPS=1 python -m bench station`` runs it beside
each run and prints, for each slow trigger, the stalls that overlap it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import time
from pathlib import Path

PRIORITY = 50
PERIOD_S = 0.005  # the meter's sleep: short enough to date a stall, long enough to cost little


def _meter(cpu: int, seconds: float, threshold_s: float) -> None:
    os.sched_setaffinity(0, {cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(PRIORITY))
    except OSError:
        print(f"hiccups: core {cpu} under the normal scheduler", file=sys.stderr, flush=True)
    end = time.monotonic() + seconds
    while (t := time.monotonic()) < end:
        time.sleep(PERIOD_S)
        over = time.monotonic() - t - PERIOD_S
        if over > threshold_s:
            os.write(1, f"{cpu} {time.time() - over:.4f} {over * 1e3:.2f}\n".encode())


def main(argv: list[str]) -> int:
    seconds = float(argv[0]) if argv else float("inf")
    threshold_s = (float(argv[1]) if len(argv) > 1 else 3.0) / 1e3
    children = []
    for cpu in sorted(os.sched_getaffinity(0)):
        pid = os.fork()
        if pid == 0:  # the meter: nothing but the loop (no interpreter state shared with it)
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            _meter(cpu, seconds, threshold_s)
            os._exit(0)
        children.append(pid)

    def stop(*_: object) -> None:
        for pid in children:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGTERM)

    signal.signal(signal.SIGTERM, stop)
    for pid in children:
        os.waitpid(pid, 0)
    return 0


def read(path: Path) -> list[tuple[int, float, float]]:
    """The stalls a run wrote to ``path``: (core, wall-clock start, ms)."""
    out = []
    for line in path.read_text().splitlines():
        cpu, t, ms = line.split()
        out.append((int(cpu), float(t), float(ms)))
    return out


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
