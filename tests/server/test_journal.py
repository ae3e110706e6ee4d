"""The durable writer on SQLite: sealing, idempotent inserts, journal compaction, replay, torn
tails, a journal that cannot be written (a real file-size limit), and the result_id filter."""

from __future__ import annotations

import csv
import io
import json
import logging
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from records import make_record

from drivers.links.result import ResultEvent
from mvpose_core.reasons import Reason
from server.store import Store, open_store
from server.store.chain import GENESIS, seal
from server.store.journal import CHUNK, PREALLOCATE, Journal, JournalCorruptError, journal_dir
from server.store.measurements import ChainConflictError, seal_link
from server.store.schemas import MeasurementFilter
from server.store.writer import DurableWriter, Sealed

HERE = Path(__file__).parent
STATION = "station1"


@pytest.fixture
def url(tmp_path: Path) -> str:
    return f"sqlite:///{tmp_path / 'store.db'}"


@pytest.fixture
def store(url: str) -> Iterator[Store]:
    s = open_store(url, STATION)
    yield s
    s.close()


def _open(url: str, data_dir: Path, **kw: float) -> DurableWriter:
    return DurableWriter.open(url, STATION, data_dir, sqlite_busy_timeout_s=0.05,
                              retry_max_s=0.2, **kw)  # type: ignore[arg-type]


def _append(writer: DurableWriter, rng: np.random.Generator, n: int,
            first: int = 1) -> list[Sealed]:
    return [writer.append(make_record(rng, STATION, trigger_id=first + i)) for i in range(n)]


def _lines(segment: Path) -> list[str]:
    """A segment's lines: they end at its first NUL byte (space written ahead of appends)."""
    return segment.read_bytes().split(b"\0", 1)[0].decode().splitlines()


def _rows(store: Store) -> list[tuple[int, int, str]]:
    return [(m.id, m.seq, m.hash) for m in store.measurements.iterate(MeasurementFilter())]


def test_append_seals_the_next_link_and_the_database_holds_it_as_sealed(
        url: str, store: Store, tmp_path: Path) -> None:
    writer = _open(url, tmp_path / "var")
    try:
        sealed = _append(writer, np.random.default_rng(1), 6)
        assert [s.seq for s in sealed] == [1, 2, 3, 4, 5, 6]
        assert sealed[0].prev_hash == GENESIS
        assert all(b.prev_hash == a.hash for a, b in zip(sealed, sealed[1:], strict=False))
        assert writer.flush(10.0)
        ids = [s.wait_id(0) for s in sealed]
        assert _rows(store) == [(i, s.seq, s.hash) for i, s in zip(ids, sealed, strict=True)]
        got = store.measurements.get(sealed[2].wait_id(0) or 0)
        assert got == sealed[2].stored()
        assert got.record == sealed[2].record and got.stored_at == sealed[2].stored_at
        report = store.measurements.verify_chain()
        assert report.ok and report.checked == 6 and report.head_hash == sealed[-1].hash
        seen: list[int] = []
        sealed[0].on_committed(seen.append)  # committed already: called at once
        assert seen == [ids[0]]
        status = writer.status()
        assert (status.up, status.head_seq, status.committed_seq, status.pending) == (
            True, 6, 6, 0)
    finally:
        writer.close()


def test_a_commit_delay_holds_the_insert_after_the_append_not_the_append(
        url: str, tmp_path: Path) -> None:
    """With commit_delay_s the database thread inserts a link that long after its append (the
    link's answer goes out first); the append itself returns at once, and the links appended
    meanwhile are committed with it."""
    with pytest.raises(ValueError, match="commit_delay_s"):
        _open(url, tmp_path / "bad", commit_delay_s=0.01, db_wait_s=0.005)
    writer = _open(url, tmp_path / "var", commit_delay_s=0.3, db_wait_s=0.0)
    try:
        t = time.monotonic()
        sealed = _append(writer, np.random.default_rng(2), 3)
        appended = time.monotonic() - t
        assert appended < 0.3 and all(s.id is None for s in sealed)
        assert writer.status().pending == 3
        assert sealed[-1].wait_id(10.0) is not None
        assert time.monotonic() - t >= 0.3
        assert writer.flush(10.0) and writer.status().committed_seq == 3
    finally:
        writer.close()


@pytest.fixture(params=["sqlite", "postgresql"])
def any_store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Store]:
    if request.param == "sqlite":
        s = open_store(f"sqlite:///{tmp_path / 'any.db'}", STATION)
    else:
        s = open_store(request.getfixturevalue("postgres_cluster").create_database(), STATION)
    yield s
    s.close()


def test_insert_links_is_idempotent_and_refuses_another_chain(any_store: Store) -> None:
    store = any_store
    rng = np.random.default_rng(2)
    links, prev = [], GENESIS
    for seq in (1, 2, 3):
        rec = make_record(rng, STATION, trigger_id=seq)
        links.append(seal_link(STATION, seq, prev, rec.triggered_at, rec))
        prev = links[-1].hash
    ids = store.measurements.insert_links(links)
    assert store.measurements.insert_links(links) == ids  # a replay is a no-op
    assert store.measurements.insert_links(links[1:]) == ids[1:]
    assert store.measurements.count() == 3

    other = make_record(rng, STATION, trigger_id=99)
    forged = seal_link(STATION, 3, links[1].hash, other.triggered_at, other)
    with pytest.raises(ChainConflictError, match="seq 3 is stored with hash"):
        store.measurements.insert_links([forged])
    after_wrong = seal_link(STATION, 4, "e" * 64, other.triggered_at, other)
    with pytest.raises(ChainConflictError, match="the database's seq 3 has hash"):
        store.measurements.insert_links([after_wrong])
    gap = seal_link(STATION, 6, "e" * 64, other.triggered_at, other)
    with pytest.raises(ChainConflictError, match="seq 5 is not in the database"):
        store.measurements.insert_links([gap])
    assert store.measurements.count() == 3 and store.measurements.verify_chain().ok


def test_compaction_keeps_the_head_and_a_restart_continues_from_it(
        url: str, store: Store, tmp_path: Path) -> None:
    data = tmp_path / "var"
    writer = _open(url, data, segment_entries=4)
    rng = np.random.default_rng(3)
    try:
        sealed = _append(writer, rng, 15)
        assert writer.flush(10.0)
    finally:
        writer.close()
    segments = sorted(journal_dir(data, STATION).glob("*.jsonl"))
    assert len(segments) == 1  # every older segment was committed and deleted
    lines = _lines(segments[0])
    assert json.loads(lines[-1])["seq"] == 15 and json.loads(lines[-1])["hash"] == sealed[-1].hash

    # The database is gone for this station (another URL, nothing listens there): the journal
    # alone knows the head, so the next result id is still 16.
    writer = DurableWriter.open(_dead_postgres_url(), STATION, data, connect_timeout_s=1)
    try:
        nxt = writer.append(make_record(rng, STATION, trigger_id=16))
        assert (nxt.seq, nxt.prev_hash, nxt.id) == (16, sealed[-1].hash, None)
        status = writer.status()
        # Not knowing what the database holds, the writer will offer it the whole last
        # segment again (13..15, no-ops when stored) and 16.
        assert not status.up and status.pending == 4 and status.last_error
    finally:
        writer.close(timeout=0)
    writer = _open(url, data)  # back on the database that holds 1..15: 16 is replayed
    try:
        assert writer.flush(10.0)
        assert [r[1] for r in _rows(store)] == list(range(1, 17))
        assert store.measurements.verify_chain().ok
    finally:
        writer.close()


def test_a_locked_database_never_holds_up_append_and_is_caught_up_after(
        url: str, store: Store, tmp_path: Path) -> None:
    """Another connection holds SQLite's write lock: appends journal and return, the database
    thread retries, and commits everything in order once the lock is released."""
    data = tmp_path / "var"
    writer = _open(url, data, db_wait_s=0.005)
    rng = np.random.default_rng(4)
    locker = sqlite3.connect(url.removeprefix("sqlite:///"), isolation_level=None)
    try:
        _append(writer, rng, 2)
        assert writer.flush(10.0)
        locker.execute("BEGIN IMMEDIATE")
        late = _append(writer, rng, 5, first=3)
        assert [s.seq for s in late] == [3, 4, 5, 6, 7] and all(s.id is None for s in late)
        done = threading.Event()
        late[-1].on_committed(lambda _id: done.set())
        assert writer.status().pending == 5
        assert writer.close(timeout=0.3) is False  # still locked: left in the journal
        locker.execute("ROLLBACK")
        assert not done.is_set()
    finally:
        locker.close()
    writer = _open(url, data)  # the restart replays 3..7 and goes on from 7
    try:
        nxt = writer.append(make_record(rng, STATION, trigger_id=8))
        assert nxt.seq == 8
        assert writer.flush(10.0)
        assert [r[1] for r in _rows(store)] == list(range(1, 9))
        assert store.measurements.verify_chain().ok
    finally:
        writer.close()


def test_the_lock_released_while_running_commits_the_backlog_and_calls_back(
        url: str, store: Store, tmp_path: Path) -> None:
    writer = _open(url, tmp_path / "var", db_wait_s=0.0)
    locker = sqlite3.connect(url.removeprefix("sqlite:///"), isolation_level=None)
    try:
        locker.execute("BEGIN IMMEDIATE")
        sealed = _append(writer, np.random.default_rng(5), 4)
        got: list[int] = []
        sealed[-1].on_committed(got.append)
        assert sealed[0].wait_id(0.2) is None
        locker.execute("ROLLBACK")
        assert sealed[-1].wait_id(10.0) is not None
        assert got == [sealed[-1].id]
        assert writer.flush(10.0) and writer.status().up
        assert [r[2] for r in _rows(store)] == [s.hash for s in sealed]
    finally:
        locker.close()
        writer.close()


def test_an_existing_database_gives_the_head_to_a_new_journal(
        url: str, store: Store, tmp_path: Path) -> None:
    """An installation from before the journal: the chain goes on where the database ends."""
    rng = np.random.default_rng(6)
    old = [store.measurements.insert(make_record(rng, STATION, trigger_id=i)) for i in (1, 2, 3)]
    writer = _open(url, tmp_path / "var")
    try:
        assert writer.head_seq == 3
        nxt = writer.append(make_record(rng, STATION, trigger_id=4))
        assert (nxt.seq, nxt.prev_hash) == (4, old[-1].hash)
        assert writer.flush(10.0)
        assert store.measurements.verify_chain().checked == 4
    finally:
        writer.close()


def test_two_journals_on_one_chain_are_a_loud_conflict(
        url: str, store: Store, tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    a = _open(url, tmp_path / "a")
    _append(a, rng, 2)
    assert a.flush(10.0)
    b = _open(url, tmp_path / "b")  # a second installation of the same station
    try:
        assert b.append(make_record(rng, STATION, trigger_id=3)).seq == 3
        assert b.flush(10.0)
        mine = a.append(make_record(rng, STATION, trigger_id=3))  # a still believes head = 2
        assert mine.seq == 3
        assert not a.flush(10.0)
        status = a.status()
        assert status.conflict and not status.up and "seq 3 is stored with hash" in (
            status.last_error or "")
    finally:
        a.close(timeout=0)
        b.close()
    with pytest.raises(ChainConflictError, match="sealed seq 3"):
        _open(url, tmp_path / "a")
    assert store.measurements.verify_chain().ok


def test_a_torn_last_line_is_cut_and_a_bad_line_inside_is_refused(
        url: str, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    data = tmp_path / "var"
    writer = _open(url, data, segment_entries=3)
    rng = np.random.default_rng(8)
    try:
        sealed = _append(writer, rng, 5)
        assert writer.flush(10.0)
    finally:
        writer.close()
    folder = journal_dir(data, STATION)
    last = sorted(folder.glob("*.jsonl"))[-1]
    good = last.read_bytes()
    end = len(good.split(b"\0", 1)[0])  # the lines end here; zeros written ahead may follow
    torn = b'{"seq": 6, "prev_hash": "' + b"\0" * 40 + b"2f9a"  # the kill hit a write
    last.write_bytes(good[:end] + torn + good[end + len(torn):])
    with caplog.at_level(logging.WARNING):
        journal = Journal.open(folder, STATION)
    journal.close()
    assert journal.head == (5, sealed[-1].hash)
    cut = last.read_bytes()  # zeros where the torn line was
    assert "torn" in caplog.text and cut[:end] == good[:end] and not cut[end:].strip(b"\0")

    lines = good[:end].split(b"\n")
    entry = json.loads(lines[1])
    entry["body"] = entry["body"].replace('"OK"', '"NOK"', 1)
    bad = b"\n".join([lines[0], json.dumps(entry).encode(), *lines[2:]])
    last.write_bytes(bad)
    with pytest.raises(JournalCorruptError, match=rf"{last.name}: line 2: body does not hash"):
        Journal.open(folder, STATION)


def test_the_journal_format_is_what_the_docs_say(url: str, tmp_path: Path) -> None:
    data = tmp_path / "var"
    writer = _open(url, data)
    try:
        sealed = _append(writer, np.random.default_rng(9), 2)
    finally:
        writer.close()
    (segment,) = journal_dir(data, STATION).glob("*.jsonl")
    assert segment.name == f"{0:020d}.jsonl"
    raw = segment.read_bytes()
    header, *links = (json.loads(line) for line in _lines(segment))
    # the lines, then only NUL bytes (written ahead of the next appends)
    end = len(b"".join(line.encode() + b"\n" for line in _lines(segment)))
    assert raw[:end].count(b"\0") == 0 and not raw[end:].strip(b"\0")
    assert header == {"journal": 1, "station": STATION, "after_seq": 0, "after_hash": GENESIS}
    for link, s in zip(links, sealed, strict=True):
        assert seal(link["prev_hash"], link["body"]) == link["hash"] == s.hash
        assert json.loads(link["body"])["seq"] == link["seq"] == s.seq


def test_a_journal_that_cannot_be_written_consumes_nothing(url: str, tmp_path: Path) -> None:
    """A real write failure: the process's file-size limit (RLIMIT_FSIZE) stops the journal
    mid-line. append raises, the head stays, and the next append after the limit is lifted
    takes the same seq; the journal verifies afterwards."""
    data = tmp_path / "var"
    code = textwrap.dedent(f"""
        import resource, signal, sys
        from pathlib import Path
        import numpy as np
        sys.path.insert(0, {str(HERE)!r})
        from records import make_record
        from server.store.writer import DurableWriter, StoreFailedError
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a killed process
        # no zeros written ahead: every append grows the file, so the limit stops one
        w = DurableWriter.open({url!r}, "station1", Path({str(data)!r}), retry_max_s=0.1,
                               journal_ahead=0)
        rng = np.random.default_rng(10)
        a = w.append(make_record(rng, "station1", trigger_id=1))
        assert w.flush(10.0)
        segment = sorted(w.journal_dir.glob("*.jsonl"))[-1]
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (segment.stat().st_size + 500, hard))
        size = segment.stat().st_size
        try:
            w.append(make_record(rng, "station1", trigger_id=2))
        except StoreFailedError as err:
            print("failed:", err)
        tail = segment.read_bytes()[size:]  # what reached the file of the failed line
        assert tail and not tail.strip(b"\\0"), "the partial line was not overwritten"
        assert w.head_seq == 1 and w.status().pending == 0
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        b = w.append(make_record(rng, "station1", trigger_id=3))
        print("next:", b.seq, b.prev_hash == a.hash)
        assert w.flush(10.0)
        w.close()
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, cwd=HERE.parents[1])
    assert out.returncode == 0, out.stderr[-2000:]
    assert "failed: station 'station1': the journal" in out.stdout
    assert "could not take seq 2" in out.stdout and "File too large" in out.stdout
    assert "next: 2 True" in out.stdout
    journal = Journal.open(journal_dir(data, STATION), STATION)
    journal.close()
    assert journal.head is not None and journal.head[0] == 2


def test_result_id_is_seq_in_summaries_and_a_filter(url: str, store: Store, tmp_path: Path) -> None:
    writer = _open(url, tmp_path / "var")
    try:
        rng = np.random.default_rng(11)
        sealed = [writer.append(make_record(rng, STATION, trigger_id=10 + i, reason=r))
                  for i, r in enumerate([Reason.OK, Reason.MARKS_MISSING, Reason.OK])]
        assert writer.flush(10.0)
    finally:
        writer.close()
    f = MeasurementFilter(result_id=sealed[1].seq)
    (only,) = store.measurements.iterate(f)
    assert only.result_id == 2 and only.record.trigger_id == 11
    assert only.model_dump(mode="json")["result_id"] == 2
    (summary,), _ = store.measurements.summary_page(f, None, 10)
    assert summary.model_dump()["result_id"] == 2 and summary.reason == "MARKS_MISSING"
    assert store.measurements.count(MeasurementFilter(result_id=4)) == 0


def _dead_postgres_url() -> str:
    """A PostgreSQL URL where nothing listens (a port just freed): connections are refused."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    return f"postgresql+psycopg://postgres@127.0.0.1:{port}/mvpose"


async def test_rest_shows_result_id_and_filters_on_it(tmp_path: Path) -> None:
    """What an MES does with the id the PLC read: find that one result over REST."""
    from apps import ENGINEER, record_some, settings
    from asgi import running

    from server.app import create_app

    reasons = [Reason.OK, Reason.MARKS_MISSING, Reason.OK]
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        stored = await record_some(state["services"], reasons)
        r = await client.get("/api/v1/measurements", params={"result_id": stored[1].seq})
        assert r.status_code == 200, r.text
        (item,) = r.json()["items"]
        assert item["result_id"] == item["seq"] == 2 and item["reason"] == "MARKS_MISSING"
        r = await client.get(f"/api/v1/measurements/{item['id']}")
        assert r.json()["result_id"] == 2
        r = await client.get("/api/v1/measurements/export", params={"format": "csv"})
        cols, *rows = list(csv.reader(io.StringIO(r.text)))
        # result_id, then the result event's shown fields (architecture.md)
        at = cols.index("result_id")
        assert cols[at + 1:] == [name for name, _ in ResultEvent.shown()]
        assert [row[at] for row in rows] == ["1", "2", "3"]
        r = await client.get("/api/v1/measurements/export", params={"format": "json"})
        assert [m["result_id"] for m in r.json()] == [1, 2, 3]
        r = await client.get("/api/v1/measurements", params={"result_id": 0})
        assert r.status_code == 422


def test_one_writer_per_journal_and_none_after_close(url: str, tmp_path: Path) -> None:
    from server.store.journal import JournalBusyError
    from server.store.writer import StoreFailedError

    data = tmp_path / "var"
    writer = _open(url, data)
    try:
        with pytest.raises(JournalBusyError, match=r"in use by another writer \(pid \d+\)"):
            _open(url, data)  # the station started twice
        writer.append(make_record(np.random.default_rng(12), STATION))
    finally:
        writer.close()
    with pytest.raises(StoreFailedError, match="could not take seq 2: .* it was closed"):
        writer.append(make_record(np.random.default_rng(13), STATION))
    again = _open(url, data)  # the lock went with the close
    try:
        assert again.head_seq == 1
    finally:
        again.close()


def test_appends_overwrite_zeros_written_ahead_and_a_reopen_continues_after_the_lines(
        url: str, tmp_path: Path) -> None:
    """Appends land on zeros the journal wrote ahead (the file does not grow with each line,
    so fdatasync flushes data only); the lines end at the first NUL, and a reopened journal
    appends right after them."""
    data = tmp_path / "var"
    rng = np.random.default_rng(12)
    writer = _open(url, data, segment_entries=1000)
    try:
        _append(writer, rng, 30)
        assert writer.flush(10.0)
        # the journal's thread writes them; the station waits for this before it is ready
        assert writer.wait_journal_ahead(30.0), "no zeros were written ahead"
        assert writer.status().journal_ahead >= PREALLOCATE // 2  # topped up below half
        size = (sealed := _append(writer, rng, 1, first=31)) and next(
            journal_dir(data, STATION).glob("*.jsonl")).stat().st_size
    finally:
        writer.close()
    (segment,) = journal_dir(data, STATION).glob("*.jsonl")
    raw = segment.read_bytes()
    end = raw.index(b"\0")
    assert len(_lines(segment)) == 32 and raw[:end].endswith(b"\n")
    assert not raw[end:].strip(b"\0") and len(raw) - end >= CHUNK // 2
    assert size == len(raw) and sealed[0].seq == 31  # the append overwrote zeros: same size

    writer = _open(url, data, segment_entries=1000)
    try:
        nxt = writer.append(make_record(rng, STATION, trigger_id=32))
        assert nxt.seq == 32
    finally:
        writer.close()
    after = segment.read_bytes()
    assert after[:end] == raw[:end] and len(_lines(segment)) == 33
    assert json.loads(_lines(segment)[-1])["seq"] == 32

    plain = tmp_path / "plain"  # no space ahead: the file is exactly its lines
    writer = DurableWriter.open(f"sqlite:///{tmp_path / 'plain.db'}", STATION, plain,
                                journal_ahead=0)
    try:
        _append(writer, rng, 3)
    finally:
        writer.close()
    (segment,) = journal_dir(plain, STATION).glob("*.jsonl")
    assert b"\0" not in segment.read_bytes() and len(_lines(segment)) == 4


def test_appends_racing_the_zeroing_thread_lose_no_line(url: str, tmp_path: Path) -> None:
    """A small space ahead (4 KiB) wakes the journal's thread every couple of appends and makes
    appends outrun its zeros: 300 appends back to back, across segments, all read back."""
    data = tmp_path / "var"
    rng = np.random.default_rng(13)
    writer = DurableWriter.open(url, STATION, data, segment_entries=120, journal_ahead=4096)
    try:
        sealed = _append(writer, rng, 300)
        assert writer.flush(30.0)
    finally:
        writer.close()
    journal = Journal.open(journal_dir(data, STATION), STATION)
    journal.close()
    assert journal.head == (300, sealed[-1].hash)
    for segment in journal_dir(data, STATION).glob("*.jsonl"):
        raw = segment.read_bytes()
        end = len(raw.split(b"\0", 1)[0])
        assert not raw[end:].strip(b"\0"), f"{segment.name}: bytes after the lines' end"
