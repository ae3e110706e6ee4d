"""The line view's figures from the store (SQLite and PostgreSQL): one shift's counts and cycle
times, and the NOKs in a row; a second store on the same database sees the same."""

from __future__ import annotations

from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from postgres import PostgresCluster
from records import T0, make_record

from mvpose_core.reasons import Reason
from server.store import Store, open_store


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


def test_one_shifts_counts_and_cycle_times(store: Store, store_url: str) -> None:
    rng = np.random.default_rng(5)
    reasons = [Reason.OK, Reason.OK, Reason.MARKS_MISSING, Reason.OK, Reason.MARKS_MISSING,
               Reason.RESIDUAL_RMS_HIGH]
    # one from the shift before
    store.measurements.insert(make_record(rng, trigger_id=99, triggered_at=T0 - timedelta(hours=1)))
    totals = []
    for k, reason in enumerate(reasons):
        rec = make_record(rng, trigger_id=k + 1, reason=reason,
                          triggered_at=T0 + timedelta(minutes=10 * k))
        totals.append(rec.timings_ms["total"])
        store.measurements.insert(rec)
    # another station's never
    other = Store(store.engine, "station2")
    other.measurements.insert(make_record(rng, "station2", trigger_id=1, triggered_at=T0))

    c = store.shifts.counts(T0, T0 + timedelta(hours=8))
    assert (c.ok, c.nok, c.total) == (3, 3, 6)
    assert c.yield_pct == pytest.approx(50.0)
    assert c.min_ms == pytest.approx(min(totals))
    assert c.max_ms == pytest.approx(max(totals))
    assert c.mean_ms == pytest.approx(np.mean(totals))
    assert store.shifts.nok_streak() == 2

    empty = store.shifts.counts(T0 + timedelta(days=1), T0 + timedelta(days=2))
    assert (empty.total, empty.yield_pct, empty.mean_ms) == (0, None, None)

    # what a restarted process reads: the same figures from the same database
    again = open_store(store_url, "station1")
    try:
        assert again.shifts.counts(T0, T0 + timedelta(hours=8)) == c
        again.measurements.insert(make_record(rng, trigger_id=7, triggered_at=T0))
        assert again.shifts.nok_streak() == 0
    finally:
        again.close()
