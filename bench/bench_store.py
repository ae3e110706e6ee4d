"""Store benchmark: one durable, chained insert on SQLite (WAL), alone and beside REST readers;
the durable writer's append (journal + at most db_wait_s) on SQLite and PostgreSQL."""

from __future__ import annotations

import os
import signal
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from bench.timing import Timing, check, measure
from mvpose_core.reasons import Reason
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import RobotConvention, to_robot
from server.metrics import Metrics
from server.store import DurableWriter, Store, open_store
from server.store.schemas import (
    CameraDetections,
    Detection,
    MeasurementFilter,
    MeasurementRecord,
    Offset,
    Residuals,
    Uncertainty,
)

TARGET_MEDIAN_MS = 2.0
TARGET_P99_MS = 5.0


def station1_record(rng: np.random.Generator, trigger_id: int) -> MeasurementRecord:
    """A record the size of a station-1 trigger: 4 cameras, 2 marks each, 5 stage timings."""
    delta = random_displacement(rng, 20.0, 2.0)
    dets = [CameraDetections(view=1, camera_id=f"cam{c}", detections=[
        Detection(mark_id=f"m{2 * c + k}", found=True, uv=tuple(rng.uniform(0, 2048, 2)),
                  quality={"contrast": 80.0, "fit_residual_px": 0.03, "axis_ratio": 0.9})
        for k in range(2)]) for c in range(4)]
    return MeasurementRecord(
        station="bench", trigger_id=trigger_id, part_id=f"VIN{trigger_id:08d}",
        triggered_at=datetime.now(UTC), recipe="floor_panel", recipe_version=3,
        calibration_id="cal-1", calibration_hash="cd" * 32, software_version="0.1.0",
        **MeasurementRecord.reason_fields(Reason.OK), detections=dets,
        T_rf_from_pf=MeasurementRecord.matrix(delta),
        offset=Offset(convention=RobotConvention.FANUC,
                      values=[float(v) for v in to_robot(delta, RobotConvention.FANUC)]),
        uncertainty=Uncertainty(sigma_mm=0.4, sigma_deg=0.03),
        residuals=Residuals(rms_px=0.1, max_px=0.3),
        timings_ms={"capture": 8.1, "detect": 1.9, "measure": 0.6, "correct": 0.4, "total": 11.3},
    )


def _inserter(store: Store, metrics: Metrics, rng: np.random.Generator):
    counter = iter(range(1, 10**9))

    def insert() -> None:
        rec = station1_record(rng, next(counter))
        stored = store.measurements.insert(rec)
        metrics.observe(rec, stored.seq)

    return insert


def run(folder: Path, synchronous: str, readers: int, repeat: int,
        rate_hz: float | None = None
        ) -> Timing:
    """Insert timing; ``readers`` threads page through results, at ``rate_hz`` each or flat out."""
    store = open_store(f"sqlite:///{folder / f'bench-{synchronous}-{readers}.db'}", "bench",
                       sqlite_synchronous=synchronous)
    stop = threading.Event()

    def read() -> None:  # an MES client asking for the newest 50 OK results
        period = 1.0 / rate_hz if rate_hz else 0.0
        next_t = time.perf_counter()
        while not stop.is_set():
            store.measurements.summary_page(MeasurementFilter(result="OK"), None, 50)
            if period:
                next_t += period
                stop.wait(max(0.0, next_t - time.perf_counter()))

    threads = [threading.Thread(target=read, daemon=True) for _ in range(readers)]
    try:
        for t in threads:
            t.start()
        load = f"{rate_hz:.0f}/s" if rate_hz else "flat out"
        label = f"insert WAL sync={synchronous}" + (
            f" + {readers} readers ({load}, 50 rows)" if readers else "")
        return measure(label, _inserter(store, Metrics(), np.random.default_rng(0)),
                       repeat=repeat, warmup=20)
    finally:
        stop.set()
        for t in threads:
            t.join()
        assert store.measurements.verify_chain().ok
        store.close()


def run_appends(folder: Path, url: str, label: str, db_wait_s: float, repeat: int,
                period_s: float | None = None) -> Timing:
    """DurableWriter.append: seal, fsynced journal line, then the commit waited <= db_wait_s.

    Back to back (``period_s`` None), each append meets the database thread still committing
    the one before (two fsyncs on one disk); paced like a line (one trigger every ``period_s``),
    the database thread has finished, as on a station."""
    pace = f", one per {period_s * 1e3:.0f} ms" if period_s else ""
    name = f"append {label} (db_wait {db_wait_s * 1e3:.0f} ms{pace})"
    data_dir = folder / name.replace(" ", "_").replace("(", "").replace(")", "").replace(",", "")
    writer = DurableWriter.open(url, "bench", data_dir, db_wait_s=db_wait_s)
    rng = np.random.default_rng(0)
    counter = iter(range(1, 10**9))
    try:
        if period_s is None:
            timing = measure(name, lambda: writer.append(station1_record(rng, next(counter))),
                             repeat=repeat, warmup=20)
        else:
            samples = []
            for _ in range(repeat + 20):
                record = station1_record(rng, next(counter))
                time.sleep(period_s)  # the line's cadence
                t0 = time.perf_counter()
                writer.append(record)
                samples.append((time.perf_counter() - t0) * 1e3)
            timing = Timing(name, np.array(samples[20:]))
    finally:
        writer.close(timeout=60.0)
    store = open_store(url, "bench")
    try:
        assert store.measurements.verify_chain().checked == repeat + 20
    finally:
        store.close()
    return timing


def disk_append(folder: Path, repeat: int) -> Timing:
    """The disk alone: append a journal-sized line (2.6 kB) to a file and fdatasync it."""
    line = b"x" * 2600 + b"\n"
    fd = os.open(folder / "disk-append", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        def append() -> None:
            os.write(fd, line)
            os.fdatasync(fd)

        return measure("append + fdatasync of a 2.6 kB line (the disk)", append, repeat=repeat)
    finally:
        os.close(fd)


def postgres_appends(folder: Path, repeat: int) -> list[Timing]:
    """Appends on a throwaway PostgreSQL 15 cluster (tests/server/postgres.py: fsync off), and
    with that cluster frozen by SIGSTOP: the append then costs the journal plus db_wait_s."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "tests" / "server"))
    from postgres import PG_BIN, start_cluster, stop_cluster

    if not (PG_BIN / "initdb").exists():
        print(f"PostgreSQL: no binaries in {PG_BIN}, skipped")
        return []
    cluster, root = start_cluster()
    try:
        out = [run_appends(folder, cluster.create_database(), "PostgreSQL 15", 0.005, repeat),
               run_appends(folder, cluster.create_database(), "PostgreSQL 15", 0.005, 300,
                           period_s=0.03)]
        url = cluster.create_database()
        writer = DurableWriter.open(url, "bench", folder / "pg-frozen", db_wait_s=0.005)
        rng = np.random.default_rng(0)
        counter = iter(range(1, 10**9))
        pids = [int((cluster.datadir / "postmaster.pid").read_text().splitlines()[0])]
        pids += [int(p.name) for p in Path("/proc").iterdir() if p.name.isdigit()
                 and _ppid(p) == pids[0]]
        for pid in pids:
            os.kill(pid, signal.SIGSTOP)
        try:
            out.append(measure("append PostgreSQL 15 frozen (db_wait 5 ms)",
                               lambda: writer.append(station1_record(rng, next(counter))),
                               repeat=repeat // 2, warmup=5))
        finally:
            for pid in pids:
                os.kill(pid, signal.SIGCONT)
        writer.close(timeout=60.0)
        return out
    finally:
        stop_cluster(cluster, root)


def _ppid(proc: Path) -> int | None:
    try:
        return int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return None


def main() -> int:
    rng_record = station1_record(np.random.default_rng(1), 1)
    print(f"record: {len(rng_record.model_dump_json())} bytes of JSON")
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as tmp:  # the disk the service uses
        folder = Path(tmp)
        full = run(folder, "FULL", 0, 500)
        normal = run(folder, "NORMAL", 0, 500)
        mes = run(folder, "FULL", 1, 500, rate_hz=50.0)
        hammer = run(folder, "FULL", 2, 200)
        # The GIL hands over every 5 ms by default; a shorter interval lets the writer back in
        # sooner after its fsync (a process-wide knob the serving process may set).
        old = sys.getswitchinterval()
        sys.setswitchinterval(0.0005)
        try:
            mes_fast = run(folder, "FULL", 1, 500, rate_hz=50.0)
        finally:
            sys.setswitchinterval(old)
        mes_fast = Timing(mes_fast.name + " switch 0.5ms", mes_fast.samples_ms)
        store = open_store(f"sqlite:///{folder / 'bench-FULL-1.db'}", "bench")
        f = MeasurementFilter(result="OK")
        page = measure("page of 50 OK summaries (the REST list query)",
                       lambda: store.measurements.summary_page(f, None, 50), repeat=100)
        store.close()
        sqlite_url = f"sqlite:///{folder / 'bench-append.db'}"
        appends = [disk_append(folder, 500),
                   run_appends(folder, sqlite_url, "SQLite FULL", 0.005, 500),
                   run_appends(folder, f"sqlite:///{folder / 'bench-append0.db'}",
                               "SQLite FULL", 0.0, 500),
                   run_appends(folder, f"sqlite:///{folder / 'bench-append-paced.db'}",
                               "SQLite FULL", 0.005, 300, period_s=0.03),
                   run_appends(folder, f"sqlite:///{folder / 'bench-append-paced0.db'}",
                               "SQLite FULL", 0.0, 300, period_s=0.03)]
        appends += postgres_appends(folder, 500)
    for t in (full, normal, mes, mes_fast, hammer, page):
        print(t.line(full if t is not full and t is not page else None))
    for t in appends:
        print(t.line())
    # The flat-out readers hold the GIL for most of each 5 ms switch interval, so the writer
    # waits at every GIL hand-over: shown for information, the target is the MES rate.
    ok = check("insert median (FULL)", full.median, TARGET_MEDIAN_MS)
    ok &= check("insert p99 (FULL)", full.p99, TARGET_P99_MS)
    ok &= check("insert p99 (FULL, MES reading 50/s)", mes.p99, TARGET_P99_MS)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
