"""The station process's memory over many triggers of `mvpose serve`, sampled from outside.

`mvpose serve` on a light scene (deploy/stations/scaling/station1_small.yaml: station 1 with
1024 x 1024 cameras, so that 20,000 triggers take minutes) with the PLC twin in its own process
triggering back to back; the station process's RSS (/proc) is read after every block of 1000
triggers. The first blocks fill caches, pools and the allocator's arenas; the growth is the
slope of a straight line through the RSS of the second half of the blocks, in KiB per trigger.
Target: flat (below 0.1 KiB a trigger, 2 MiB over 20,000).

The flat target is for leaks: memory beyond the station's designed bounded buffers. The largest
per-trigger one is the drift watch's history (docs/calibration.md, "Drift watch"): 32 bytes a
camera and 16 a trigger, filled up to the station file's ``drift.history`` triggers after the
watch's learning window (2.7 MiB for 4 cameras at the default 20,000, which this run would not
pass). The bench's copy of the station file keeps a small history (2,000) so that the watch
reaches its cap within the first half of the run; both caps are printed.

Environment: MVPOSE_BENCH_MEMORY_TRIGGERS (default 20000), MVPOSE_BENCH_MEMORY_STATION (a
station file name under deploy/stations or deploy/stations/scaling; default station1_small),
MVPOSE_BENCH_MEMORY_DRIFT_HISTORY (the drift watch's history, default 2000).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from bench.bench_station import TWIN_POLL_MS, station_file
from bench.serve_process import rss_kb, start_serve
from bench.twin_process import TwinProcess
from mvpose_core.drift import DriftOptions
from mvpose_core.station import load_station
from server.drift import service_history_bytes

TRIGGERS = int(os.environ.get("MVPOSE_BENCH_MEMORY_TRIGGERS", "20000"))
STATION = os.environ.get("MVPOSE_BENCH_MEMORY_STATION", "station1_small")
BLOCK = 1000
TARGET_KIB = 0.1
DRIFT_HISTORY = int(os.environ.get("MVPOSE_BENCH_MEMORY_DRIFT_HISTORY", "2000"))


def with_drift_history(path: Path, history: int) -> int:
    """Set the station file's drift history; the (view, camera) pairs the watch follows."""
    data = yaml.safe_load(path.read_text())
    data["drift"] = {"history": history}
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return len(list(load_station(path).iter_view_cameras()))


def main() -> int:
    with tempfile.TemporaryDirectory() as t:
        tmp = Path(t)
        path = station_file(STATION, tmp)
        cams = with_drift_history(path, DRIFT_HISTORY)
        default = DriftOptions().history
        warmup = DriftOptions().warmup
        print(f"  drift history: {DRIFT_HISTORY} triggers of {cams} cameras, "
              f"{service_history_bytes(cams, DRIFT_HISTORY) / 1024:.0f} KiB at its cap "
              f"(full after ~{DRIFT_HISTORY + warmup} triggers); at the default {default}: "
              f"{service_history_bytes(cams, default) / 2**20:.1f} MiB "
              f"({service_history_bytes(cams, 1) / 1024:.3f} KiB a trigger until "
              f"~{default + warmup} triggers)", flush=True)
        if DRIFT_HISTORY + warmup > TRIGGERS // 2:
            print(f"  note: the drift history fills after the run's first half ({TRIGGERS // 2} "
                  "triggers): its growth counts in the slope", flush=True)
        serve = start_serve(path, STATION, tmp / "data",
                            extra_env={"MVPOSE_IMAGES_OK_EVERY": str(10**6)})
        rows: list[tuple[int, int, float, float]] = []  # triggers so far, RSS KiB, p50, p99
        nok = 0
        try:
            twin = TwinProcess(serve.plc_port, tmp / "twin.log", 0.0, TWIN_POLL_MS)
            try:
                rows.append((0, rss_kb(serve.station_pid), float("nan"), float("nan")))
                done = 0
                t0 = time.monotonic()
                while done < TRIGGERS:
                    n = min(BLOCK, TRIGGERS - done)
                    res = twin.block(done + 1, n)
                    done += n
                    nok += int(res["nok"])
                    rt = np.array(res["roundtrip_ms"])
                    rows.append((done, rss_kb(serve.station_pid), float(np.median(rt)),
                                 float(np.percentile(rt, 99))))
                    print(f"    {done:6d} triggers  station RSS {rows[-1][1] / 1024:7.1f} MiB  "
                          f"roundtrip p50 {rows[-1][2]:5.1f} p99 {rows[-1][3]:5.1f} ms  "
                          f"({time.monotonic() - t0:.0f} s)", flush=True)
            finally:
                twin.close()
        finally:
            serve.stop()
    half = rows[len(rows) // 2:]
    x = np.array([r[0] for r in half], dtype=float)
    y = np.array([r[1] for r in half], dtype=float)
    slope = float(np.polyfit(x, y, 1)[0]) if len(half) >= 2 else float("nan")
    total = (rows[-1][1] - rows[1][1]) / 1024 if len(rows) > 2 else float("nan")
    print(f"  {STATION}: {TRIGGERS} triggers, {nok} NOK; station RSS {rows[0][1] / 1024:.1f} MiB "
          f"at ready, {rows[1][1] / 1024:.1f} after {BLOCK}, {rows[-1][1] / 1024:.1f} at the end "
          f"({total:+.1f} MiB after the first block); slope over the second half "
          f"{slope:+.3f} KiB/trigger")
    ok = slope <= TARGET_KIB and nok == 0
    print(f"  target station RSS growth: {slope:.3f} KiB/trigger <= {TARGET_KIB} ... "
          f"{'OK' if ok else 'MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
