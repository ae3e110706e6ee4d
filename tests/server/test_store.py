"""The store on SQLite and on a real PostgreSQL 15: schema, chained append-only records, queries."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from postgres import PostgresCluster
from pydantic import ValidationError
from records import T0, make_record

from mvpose_core.reasons import Reason
from server.errors import InvalidInputError, NotFoundError
from server.store import Store, open_store
from server.store.db import head_revision
from server.store.models import Base
from server.store.schemas import MeasurementFilter


@pytest.fixture(params=["sqlite", "postgresql"])
def store_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'store.db'}"
    cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
    return cluster.create_database()


@pytest.fixture
def store(store_url: str) -> Iterator[Store]:
    s = open_store(store_url, "station1")
    yield s
    s.close()


def _disable_append_only(store: Store) -> None:
    """What an attacker with database access would do first."""
    with store.engine.begin() as conn:
        if store.dialect == "sqlite":
            conn.execute(sa.text("DROP TRIGGER measurements_no_update"))
            conn.execute(sa.text("DROP TRIGGER measurements_no_delete"))
        else:
            conn.execute(
                sa.text("ALTER TABLE measurements DISABLE TRIGGER measurements_append_only"))


def test_migrations_reach_head_and_match_the_models(store: Store) -> None:
    assert store.revision() == head_revision()
    with store.engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn), Base.metadata)
    assert diff == []


def test_insert_round_trips_and_chains(store: Store) -> None:
    rng = np.random.default_rng(1)
    stored = [store.measurements.insert(make_record(rng, trigger_id=i)) for i in range(1, 6)]
    assert [s.seq for s in stored] == [1, 2, 3, 4, 5]
    assert stored[0].prev_hash == "0" * 64
    for a, b in zip(stored, stored[1:], strict=False):
        assert b.prev_hash == a.hash
    got = store.measurements.get(stored[2].id)
    assert got == stored[2]
    assert got.record.detections == stored[2].record.detections
    report = store.measurements.verify_chain()
    assert report.ok and report.checked == 5 and report.head_hash == stored[-1].hash


def test_measurements_are_append_only_in_the_database(store: Store) -> None:
    m = store.measurements.insert(make_record(np.random.default_rng(2)))
    statements = ["UPDATE measurements SET result = 'NOK'", "DELETE FROM measurements"]
    if store.dialect == "postgresql":
        statements.append("TRUNCATE measurements CASCADE")
    for statement in statements:
        with pytest.raises(sa.exc.DBAPIError, match="append-only"), store.engine.begin() as conn:
            conn.execute(sa.text(statement))
    assert store.measurements.get(m.id) == m


@pytest.mark.parametrize("tamper", ["body", "column", "delete", "hash"])
def test_chain_verification_finds_the_first_tampered_link(store: Store, tamper: str) -> None:
    rng = np.random.default_rng(3)
    stored = [store.measurements.insert(make_record(rng, trigger_id=i)) for i in range(1, 8)]
    victim = stored[3]
    _disable_append_only(store)
    with store.engine.begin() as conn:
        if tamper == "body":
            body = conn.execute(sa.text("SELECT body FROM measurements WHERE id = :i"),
                                {"i": victim.id}).scalar_one()
            conn.execute(sa.text("UPDATE measurements SET body = :b WHERE id = :i"),
                         {"b": body.replace('"OK"', '"NOK"', 1), "i": victim.id})
        elif tamper == "column":
            conn.execute(sa.text("UPDATE measurements SET part_id = 'FORGED' WHERE id = :i"),
                         {"i": victim.id})
        elif tamper == "delete":
            conn.execute(sa.text("DELETE FROM measurements WHERE id = :i"), {"i": victim.id})
        else:  # a consistent rewrite of one link still breaks the next one
            conn.execute(sa.text("UPDATE measurements SET hash = :h WHERE id = :i"),
                         {"h": "f" * 64, "i": victim.id})
    report = store.measurements.verify_chain()
    assert not report.ok
    assert report.first_bad_seq == (victim.seq if tamper != "delete" else victim.seq + 1)
    assert report.checked == victim.seq - 1
    assert report.problem


def test_filters_and_cursor_paging(store: Store) -> None:
    rng = np.random.default_rng(4)
    reasons = [Reason.OK, Reason.OK, Reason.MARKS_MISSING, Reason.OK,
               Reason.RESIDUAL_RMS_HIGH]
    ids = []
    for i in range(1, 26):
        rec = make_record(rng, trigger_id=i, reason=reasons[i % 5],
                          recipe="door" if i % 3 == 0 else "floor_panel")
        ids.append(store.measurements.insert(rec).id)
    seen, cursor = [], None
    while True:
        page, cursor = store.measurements.page(MeasurementFilter(), cursor, 7)
        seen += [m.id for m in page]
        if cursor is None:
            break
    assert seen == sorted(ids, reverse=True)

    def ids_of(**kw: object) -> set[int]:
        return {m.record.trigger_id for m in store.measurements.iterate(MeasurementFilter(**kw))}

    assert ids_of(result="NOK") == {i for i in range(1, 26) if reasons[i % 5] != Reason.OK}
    missing = int(Reason.MARKS_MISSING)
    assert ids_of(reason_code=missing) == {i for i in range(1, 26) if i % 5 == 2}
    assert ids_of(recipe="door") == {i for i in range(1, 26) if i % 3 == 0}
    assert ids_of(part_id="VIN000007") == {7}
    # triggered_at = T0 + 30 s * trigger_id; the window is half-open [since, until)
    assert ids_of(since=T0 + timedelta(seconds=300), until=T0 + timedelta(seconds=450)) == {
        10, 11, 12, 13, 14}
    assert store.measurements.count(MeasurementFilter(result="OK")) == len(ids_of(result="OK"))


def test_paging_is_stable_while_records_arrive(store: Store) -> None:
    rng = np.random.default_rng(5)
    first = [store.measurements.insert(make_record(rng, trigger_id=i)).id for i in range(1, 11)]
    page1, cursor = store.measurements.page(MeasurementFilter(), None, 4)
    store.measurements.insert(make_record(rng, trigger_id=99))
    rest = []
    while cursor is not None:
        page, cursor = store.measurements.page(MeasurementFilter(), cursor, 4)
        rest += page
    assert [m.id for m in page1 + rest] == sorted(first, reverse=True)


def test_index_paging_oldest_first_with_the_trigger_id_filter(store: Store) -> None:
    """summaries_from (OPC UA's GetResultListFiltered): oldest first from an index, the total
    of all matches, and records arriving meanwhile land at the end."""
    rng = np.random.default_rng(6)
    for i in range(1, 11):
        store.measurements.insert(make_record(rng, trigger_id=100 + i % 3))
    total, page = store.measurements.summaries_from(MeasurementFilter(), 2, 3)
    assert total == 10 and [m.result_id for m in page] == [3, 4, 5]
    store.measurements.insert(make_record(rng, trigger_id=101))
    total, found = store.measurements.summaries_from(MeasurementFilter(trigger_id=101), 0, 50)
    matches = list(found)
    assert total == 5 and [m.result_id for m in matches] == [1, 4, 7, 10, 11]
    assert {m.trigger_id for m in matches} == {101}
    total, page = store.measurements.summaries_from(MeasurementFilter(trigger_id=101), 4, 0)
    assert total == 5 and list(page) == []


def test_bad_cursor_and_naive_times_are_the_callers_error(store: Store) -> None:
    with pytest.raises(InvalidInputError, match="cursor"):
        store.measurements.page(MeasurementFilter(), "not-a-cursor", 5)
    with pytest.raises(InvalidInputError, match="time zone"):
        store.measurements.page(MeasurementFilter(since=T0.replace(tzinfo=None)), None, 5)
    with pytest.raises(NotFoundError, match="measurement 12345"):
        store.measurements.get(12345)


def test_concurrent_writers_keep_one_unbroken_chain(store: Store) -> None:
    rng = np.random.default_rng(6)
    records = [make_record(rng, trigger_id=i) for i in range(40)]
    errors: list[BaseException] = []

    def write(chunk: list) -> None:
        try:
            for r in chunk:
                store.measurements.insert(r)
        except BaseException as err:  # surfaced by the assertion below
            errors.append(err)

    threads = [threading.Thread(target=write, args=(records[k::4],)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []
    report = store.measurements.verify_chain()
    assert report.ok and report.checked == 40


def test_two_writers_of_one_station_take_turns_without_breaking_the_chain(store_url: str) -> None:
    """Each writer remembers the head it left; after the other one appended, its next append
    collides on (station, seq), reads the head again and goes on from there."""
    a, b = open_store(store_url, "station1"), open_store(store_url, "station1")
    try:
        rng = np.random.default_rng(9)
        stored = []
        for i in range(6):
            writer = a if i % 3 else b  # b, a, a, b, a, a: each sees the other's appends
            stored.append(writer.measurements.insert(make_record(rng, trigger_id=i)))
        assert [m.seq for m in stored] == [1, 2, 3, 4, 5, 6]
        assert all(m.prev_hash == p.hash for p, m in zip(stored, stored[1:], strict=False))
        report = a.measurements.verify_chain()
        assert report.ok and report.checked == 6
    finally:
        a.close()
        b.close()


def test_stations_have_independent_chains_in_one_database(store_url: str) -> None:
    a, b = open_store(store_url, "station1"), open_store(store_url, "station2")
    try:
        rng = np.random.default_rng(7)
        for i in range(3):
            a.measurements.insert(make_record(rng, "station1", trigger_id=i))
            b.measurements.insert(make_record(rng, "station2", trigger_id=i))
        assert a.measurements.verify_chain().checked == 3
        assert b.measurements.verify_chain().checked == 3
        stations = {m.record.station for m in b.measurements.iterate(MeasurementFilter())}
        assert stations == {"station2"}
        with pytest.raises(InvalidInputError, match="station2"):
            a.measurements.insert(make_record(rng, "station2"))
    finally:
        a.close()
        b.close()


def test_records_survive_reopening_and_the_chain_continues(store_url: str) -> None:
    rng = np.random.default_rng(8)
    s = open_store(store_url, "station1")
    last = [s.measurements.insert(make_record(rng, trigger_id=i)) for i in range(3)][-1]
    s.close()
    s = open_store(store_url, "station1")  # runs the migrations again: a no-op at head
    try:
        nxt = s.measurements.insert(make_record(rng, trigger_id=3))
        assert nxt.seq == 4 and nxt.prev_hash == last.hash
        assert s.measurements.verify_chain().ok
    finally:
        s.close()


def test_versions_add_activate_and_read_back(store: Store) -> None:
    v = store.versions
    one = v.add("recipe", "door", {"marks": 3, "ref": [0, 0, 0]}, "alice", "first")
    two = v.add("recipe", "door", {"marks": 3, "ref": [1, 0, 0]}, "bob")
    assert (one.version, two.version) == (1, 2) and not two.active
    assert v.activate("recipe", "door", 1, "carol").active
    info, content = v.content("recipe", "door")
    assert info.version == 1 and content == {"marks": 3, "ref": [0, 0, 0]}
    assert v.find("recipe", "door", {"ref": [1, 0, 0], "marks": 3}).version == 2  # key order
    assert v.find("recipe", "door", {"marks": 4}) is None
    assert [s.active_version for s in v.names("recipe")] == [1]
    assert [i.active for i in v.versions("recipe", "door")] == [True, False]
    v.activate("recipe", "door", 2, "carol")
    assert v.content("recipe", "door")[0].version == 2
    with pytest.raises(NotFoundError, match="no version 7"):
        v.activate("recipe", "door", 7, "carol")
    with pytest.raises(NotFoundError, match="does not exist"):
        v.versions("calibration", "door")


def test_record_schema_refuses_inconsistent_records() -> None:
    rng = np.random.default_rng(9)
    good = make_record(rng)
    data = good.model_dump()
    for change, match in (({"reason_code": 3}, "does not agree"),
                          ({"T_rf_from_pf": None}, "needs T_rf_from_pf"),
                          ({"timings_ms": {"total": float("nan")}}, "finite"),
                          ({"triggered_at": T0.replace(tzinfo=None)}, "timezone"),
                          ({"offset": {"convention": "abb", "values": [1.0] * 6}}, "7 values"),
                          ({"surprise": 1}, "Extra inputs")):
        with pytest.raises(ValidationError, match=match):
            type(good).model_validate({**data, **change})


def test_stations_starting_together_migrate_once(postgres_cluster: PostgresCluster) -> None:
    """Two station processes open a fresh shared PostgreSQL database at the same moment."""
    url = postgres_cluster.create_database()
    code = textwrap.dedent(f"""
        import sys
        from server.store import open_store
        store = open_store({url!r}, sys.argv[1])
        print(store.revision())
        store.close()
    """)
    procs = [subprocess.Popen([sys.executable, "-c", code, f"station{k}"], text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              cwd=Path(__file__).parents[2]) for k in (1, 2)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [err[-500:] for _, err in outs]
    assert [out.strip() for out, _ in outs] == [head_revision()] * 2


def test_a_verified_token_is_remembered_for_the_ttl_and_forgotten_on_a_change(store: Store) -> None:
    """Two servers on one database: a revoke through one takes effect in the other within the
    TTL (a clock handed in, not slept on), and at once in the server that made it."""
    from server.store.tokens import TokenRepository

    now = [100.0]
    here = TokenRepository(store.engine, verified_ttl_s=2.0, clock=lambda: now[0])
    other = TokenRepository(store.engine, verified_ttl_s=2.0, clock=lambda: now[0])
    here.create("mes", "read", "a" * 64)
    assert here.recent("a" * 64) is None  # never looked up yet: the database decides
    assert here.by_hash("a" * 64) is not None
    assert here.recent("a" * 64) is not None
    assert here.by_hash("b" * 64) is None and here.recent("b" * 64) is None  # unknown: not kept

    other.revoke("mes")  # through the other server
    now[0] += 1.9
    assert here.recent("a" * 64) is not None  # still within the TTL here
    assert here.by_hash("a" * 64) is None  # the database already says revoked ...
    assert here.recent("a" * 64) is None  # ... and a revoked look-up is not remembered
    here.upsert_secret("mes", "read", "a" * 64)  # live again, through this server
    assert here.by_hash("a" * 64) is not None
    now[0] += 2.0
    assert here.recent("a" * 64) is None  # the TTL passed: asked again

    assert here.by_hash("a" * 64) is not None and here.recent("a" * 64) is not None
    here.revoke("mes")  # through this server: forgotten at once
    assert here.recent("a" * 64) is None and here.by_hash("a" * 64) is None
