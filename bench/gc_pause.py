"""What Python's cyclic garbage collector costs the trigger path, with and without the station's
start-up heap frozen (server/station/heap.py).

``python -m bench.gc_pause [--triggers N]``: station 1's trigger work alone
(bench/stage_reference.py) with the part moved through the station bench's 8 places, N
triggers (1000) as the heap is after start-up, then N more after ``heap.freeze()``. Prints, per
condition, the collections of each generation (how many, the longest) and the triggers'
processing p50 / p99 / longest, ms. A collection of the oldest generation traverses every
object of the process; it comes when enough objects have survived the younger ones, so it may
not fall within N triggers of a condition (then its count is 0).
"""

from __future__ import annotations

import argparse
import gc
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.bench_station import N_POSES, station_file
from bench.moving_part import line_poses


def main(argv: list[str] | None = None) -> int:
    from bench.stage_reference import AloneStation
    from server.station import heap

    ap = argparse.ArgumentParser(prog="python -m bench.gc_pause")
    ap.add_argument("--triggers", type=int, default=1000, help="triggers per condition (1000)")
    args = ap.parse_args(argv)
    started: list[float] = []
    pauses: dict[int, list[float]] = {}

    def timed(phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            started.append(time.perf_counter())
        elif started:
            pauses.setdefault(info["generation"], []).append(
                (time.perf_counter() - started.pop()) * 1e3)

    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        alone = AloneStation(station_file("station1", tmp), tmp / "alone", keep_poses=N_POSES)
        poses = line_poses(alone.book.selected.config)  # type: ignore[union-attr]
        print(f"  station1, the trigger's work alone, {args.triggers} triggers per condition; "
              f"{len(gc.get_objects())} objects tracked after start-up", flush=True)
        gc.callbacks.append(timed)
        try:
            for cond in ("start-up heap collected", "start-up heap frozen"):
                if cond.endswith("frozen"):
                    frozen = heap.freeze()
                    cond += f" ({frozen} objects)"
                pauses.clear()
                processing = []
                for k in range(args.triggers):
                    alone.scene.set_part_pose(poses[k % len(poses)].T_rf_from_pf)
                    processing.append(alone.trigger()["processing"])
                gens = ", ".join(
                    f"gen {g}: {len(pauses.get(g, []))} (longest "
                    f"{max(pauses.get(g, [0.0])):.2f} ms)" for g in (0, 1, 2))
                print(f"  {cond}: collections {gens}; processing p50 "
                      f"{np.median(processing):.2f}, p99 {np.percentile(processing, 99):.2f}, "
                      f"longest {max(processing):.2f} ms", flush=True)
        finally:
            gc.callbacks.remove(timed)
            heap.thaw()
            alone.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
