"""The durable writer against real faults of a real PostgreSQL 15: the server frozen (SIGSTOP),
stopped (immediate) and started again, and the writer process killed (SIGKILL).

The cluster here is this module's own (tests/server/postgres.py), not the session's shared one:
freezing or stopping it must not touch another test's database.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from postgres import PG_BIN, PostgresCluster, _as_owner, start_cluster, stop_cluster
from records import make_record

from server.errors import StoreUnavailableError
from server.store import open_store
from server.store.journal import journal_dir
from server.store.schemas import MeasurementFilter
from server.store.writer import DurableWriter, Sealed

HERE = Path(__file__).parent
STATION = "station1"
DB_WAIT_S = 0.005
# "Never waits on the database": an append is one fsynced journal write plus at most DB_WAIT_S.
# An append that waited for the database instead would take the writer's connect timeout (1 s)
# or stay blocked until the frozen server is let go (after all its appends). SLACK_S tells the
# two apart with room for a thread that wakes late on a busy 2-core machine; it is no latency
# figure (those are in `make bench`). The journal write is the disk's own time.
SLACK_S = 0.5


@pytest.fixture(scope="module")
def cluster() -> Iterator[tuple[PostgresCluster, Path]]:
    c, root = start_cluster()
    try:
        yield c, root
    finally:
        _signal_all(c, signal.SIGCONT)  # never leave a frozen server behind
        stop_cluster(c, root)


def _server_pids(c: PostgresCluster) -> list[int]:
    """The postmaster and every process it forked (backends, checkpointer, WAL writer …)."""
    postmaster = int((c.datadir / "postmaster.pid").read_text().splitlines()[0])
    children = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == postmaster:
                children.append(int(entry.name))
    return [postmaster, *children]


def _signal_all(c: PostgresCluster, sig: signal.Signals) -> None:
    if not (c.datadir / "postmaster.pid").exists():
        return
    for pid in _server_pids(c):
        with contextlib.suppress(ProcessLookupError):  # a backend that ended meanwhile
            os.kill(pid, sig)


def _pg_ctl(c: PostgresCluster, root: Path, action: str) -> None:
    """Stop (immediate: a crash as far as the clients see) or start the cluster again on its
    port, with the options tests/server/postgres.py started it with."""
    opts = (f"-p {c.port} -k {root / 'sock'} -c listen_addresses=127.0.0.1 -c fsync=off "
            "-c synchronous_commit=off -c full_page_writes=off -c shared_buffers=16MB")
    cmd = [str(PG_BIN / "pg_ctl"), "-D", str(c.datadir), "-w", "-t", "60"]
    cmd += ["-m", "immediate", "stop"] if action == "stop" else [
        "-o", opts, "-l", str(root / "log"), "start"]
    subprocess.run(_as_owner(cmd), check=True, capture_output=True)


def _timed_appends(writer: DurableWriter, rng: np.random.Generator, first: int, n: int,
                   every_s: float = 0.02) -> tuple[list[Sealed], list[float]]:
    """``n`` triggers paced like a line (one every ``every_s``); each append's duration."""
    sealed, took = [], []
    for i in range(n):
        rec = make_record(rng, STATION, trigger_id=first + i)
        t0 = time.perf_counter()
        sealed.append(writer.append(rec))
        took.append(time.perf_counter() - t0)
        beyond_journal = took[-1] - sealed[-1].journal_ms / 1e3
        assert beyond_journal < DB_WAIT_S + SLACK_S, (sealed[-1].seq, took[-1], beyond_journal)
        time.sleep(every_s)  # the line's cadence, not a wait for a condition
    return sealed, took


def _journalled(data_dir: Path) -> dict[int, str]:
    out = {}
    for segment in sorted(journal_dir(data_dir, STATION).glob("*.jsonl")):
        # a segment's lines end at its first NUL byte (space written ahead of the appends)
        for line in segment.read_bytes().split(b"\0", 1)[0].decode().splitlines()[1:]:
            link = json.loads(line)
            out[link["seq"]] = link["hash"]
    return out


def _assert_stored_exactly(url: str, sealed: list[Sealed]) -> None:
    """The database holds each returned seq once, with the hash append returned, chain intact."""
    store = open_store(url, STATION)
    try:
        rows = [(m.seq, m.hash) for m in store.measurements.iterate(MeasurementFilter())]
        assert rows == [(s.seq, s.hash) for s in sealed]
        assert [s.seq for s in sealed] == list(range(1, len(sealed) + 1))
        report = store.measurements.verify_chain()
        assert report.ok and report.checked == len(sealed), report
    finally:
        store.close()


def _open(url: str, data_dir: Path) -> DurableWriter:
    return DurableWriter.open(url, STATION, data_dir, db_wait_s=DB_WAIT_S, connect_timeout_s=1,
                              retry_max_s=0.2, stall_s=0.2)


def test_the_writer_connection_has_bounded_waits(
        cluster: tuple[PostgresCluster, Path], tmp_path: Path) -> None:
    c, _ = cluster
    writer = DurableWriter.open(c.create_database(), STATION, tmp_path / "var",
                                statement_timeout_s=3.0)
    try:
        with writer.engine.connect() as conn:
            shown = {k: conn.execute(sa.text(f"SHOW {k}")).scalar_one()
                     for k in ("statement_timeout", "lock_timeout")}
            dbapi = conn.connection.dbapi_connection
            assert dbapi is not None
            client = dbapi.info.get_parameters()  # libpq's own settings of this connection
    finally:
        writer.close()
    assert shown == {"statement_timeout": "3s", "lock_timeout": "3s"}
    assert (client["connect_timeout"], client["tcp_user_timeout"], client["keepalives"]) == (
        "2", "6000", "1")


def test_a_frozen_database_never_holds_up_an_append(
        cluster: tuple[PostgresCluster, Path], tmp_path: Path) -> None:
    c, _ = cluster
    url = c.create_database()
    data = tmp_path / "var"
    writer = _open(url, data)
    rng = np.random.default_rng(1)
    try:
        before, _ = _timed_appends(writer, rng, 1, 10, every_s=0.0)
        assert writer.flush(30.0)
        _signal_all(c, signal.SIGSTOP)
        try:
            frozen, _ = _timed_appends(writer, rng, 11, 25)
            status = writer.status()
            on_disk = _journalled(data)
            t0 = time.perf_counter()  # a start-up facing the frozen server gives up in time
            with pytest.raises(StoreUnavailableError, match="cannot be reached"):
                DurableWriter.open(url, "station2", tmp_path / "other", connect_timeout_s=1)
            assert time.perf_counter() - t0 < 10
        finally:
            _signal_all(c, signal.SIGCONT)
        assert all(s.id is None for s in frozen)
        assert not status.up and status.pending == 25 and status.head_seq == 35
        assert status.oldest_pending_s is not None and status.oldest_pending_s > 0.2
        assert all(on_disk[s.seq] == s.hash for s in frozen)
        after, _ = _timed_appends(writer, rng, 36, 5, every_s=0.0)
        assert writer.flush(30.0)
        assert writer.status().up and all(s.id is not None for s in frozen)
    finally:
        writer.close()
    _assert_stored_exactly(url, before + frozen + after)


def test_a_stopped_and_restarted_database_loses_nothing(
        cluster: tuple[PostgresCluster, Path], tmp_path: Path) -> None:
    """Stopped mid-run, the station even restarts while it is down: the journal knows the head
    (a new data dir does not, and start-up says so); once it is back, everything is stored."""
    c, root = cluster
    url = c.create_database()
    data = tmp_path / "var"
    writer = _open(url, data)
    rng = np.random.default_rng(2)
    stopped = False
    try:
        sealed, _ = _timed_appends(writer, rng, 1, 10, every_s=0.0)
        assert writer.flush(30.0)
        _pg_ctl(c, root, "stop")
        stopped = True
        down, _ = _timed_appends(writer, rng, 11, 10)
        sealed += down
        status = writer.status()
        assert not status.up and status.pending == 10 and "OperationalError" in (
            status.last_error or "")
        assert writer.close(timeout=0) is False

        with pytest.raises(StoreUnavailableError, match="journal .* is empty"):
            _open(url, tmp_path / "fresh")
        writer = _open(url, data)  # the database still down: the journal has the head
        assert writer.head_seq == 20
        down, _ = _timed_appends(writer, rng, 21, 10)
        sealed += down
        ids_later = down
        _pg_ctl(c, root, "start")
        stopped = False
        more, _ = _timed_appends(writer, rng, 31, 5, every_s=0.0)
        sealed += more
        assert writer.flush(30.0)
        assert all(s.wait_id(0) is not None for s in ids_later + more)
    finally:
        writer.close()
        if stopped:
            _pg_ctl(c, root, "start")
    _assert_stored_exactly(url, sealed)


_KILLED_WRITER = """
import sys
from pathlib import Path
import numpy as np
sys.path.insert(0, {here!r})
from records import make_record
from server.store.writer import DurableWriter
w = DurableWriter.open({url!r}, "station1", Path({data!r}), db_wait_s=0.005,
                       connect_timeout_s=1, retry_max_s=0.2)
rng = np.random.default_rng({seed})
for i in range(1, 100000):
    s = w.append(make_record(rng, "station1", trigger_id=i))
    print(s.seq, s.hash, flush=True)
"""


def _run_and_kill(url: str, data: Path, seed: int, after: int,
                  while_frozen: PostgresCluster | None) -> dict[int, str]:
    """Start a writer process, SIGKILL it once it has returned ``after`` results (with the
    database frozen for the last ones when ``while_frozen``); what it returned."""
    code = textwrap.dedent(_KILLED_WRITER.format(here=str(HERE), url=url, data=str(data),
                                                 seed=seed))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=HERE.parents[1])
    assert proc.stdout is not None
    returned: dict[int, str] = {}
    try:
        while len(returned) < after:
            line = proc.stdout.readline()
            assert line, f"writer process ended: {proc.stderr.read() if proc.stderr else ''}"
            seq, digest = line.split()
            returned[int(seq)] = digest
            if while_frozen is not None and len(returned) == after // 2:
                _signal_all(while_frozen, signal.SIGSTOP)
    finally:
        proc.kill()
        rest, _ = proc.communicate(timeout=60)
        if while_frozen is not None:
            _signal_all(while_frozen, signal.SIGCONT)
    for line in rest.splitlines():  # results it returned between our last read and the kill
        parts = line.split()
        if len(parts) == 2 and len(parts[1]) == 64:
            returned[int(parts[0])] = parts[1]
    return returned


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_a_killed_writer_process_loses_nothing_and_reuses_no_seq(
        backend: str, cluster: tuple[PostgresCluster, Path], tmp_path: Path) -> None:
    c, _ = cluster
    url = f"sqlite:///{tmp_path / 'store.db'}" if backend == "sqlite" else c.create_database()
    data = tmp_path / "var"
    returned = _run_and_kill(url, data, seed=3, after=30,
                             while_frozen=c if backend == "postgresql" else None)
    assert sorted(returned) == list(range(1, len(returned) + 1))
    if backend == "postgresql":  # those of the frozen half were in the journal only
        store = open_store(url, STATION)
        try:
            assert store.measurements.count() < len(returned) - 5
        finally:
            store.close()
    writer = _open(url, data)
    try:
        assert writer.head_seq >= max(returned)  # the head never goes back: no seq reused
        nxt = writer.append(make_record(np.random.default_rng(4), STATION, trigger_id=999))
        assert nxt.seq == writer.head_seq and nxt.seq > max(returned)
        assert writer.flush(30.0)
    finally:
        writer.close()
    store = open_store(url, STATION)
    try:
        rows = {m.seq: m.hash for m in store.measurements.iterate(MeasurementFilter())}
        assert all(rows.get(seq) == digest for seq, digest in returned.items())
        assert sorted(rows) == list(range(1, nxt.seq + 1)) and rows[nxt.seq] == nxt.hash
        report = store.measurements.verify_chain()
        assert report.ok and report.checked == nxt.seq
    finally:
        store.close()
