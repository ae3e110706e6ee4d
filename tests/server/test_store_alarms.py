"""Alarms in the store (SQLite and PostgreSQL): raising is idempotent per source and code while
active, clearing and acknowledging are recorded once with who and when, and all of it survives
a restart; with a topic each transition queues its MQTT message in the outbox."""

from __future__ import annotations

import json
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest
from postgres import PostgresCluster
from records import T0
from sqlalchemy import text

from server.errors import NotFoundError
from server.store import Store, open_store
from server.store.alarms import AlarmFilter
from server.store.outbox import Outbox


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


def test_raise_is_idempotent_while_active_and_survives_a_restart(store: Store,
                                                                   store_url: str) -> None:
    a, new = store.alarms.raise_("link:modbus", "LINK_DOWN", "high", "link modbus is down",
                                 {"link": "modbus"}, at=T0)
    assert new and a.active and not a.acknowledged
    again, new2 = store.alarms.raise_("link:modbus", "LINK_DOWN", "high", "other text", at=T0)
    assert not new2 and again.id == a.id and again.text == "link modbus is down"
    assert again.text_key == "alarm.LINK_DOWN" and again.text_args == {"link": "modbus"}

    # a restart (a new store on the same database) finds the same active alarm
    store.close()
    reopened = open_store(store_url, "station1")
    try:
        found, new3 = reopened.alarms.raise_("link:modbus", "LINK_DOWN", "high", "x")
        assert not new3 and found.id == a.id
        cleared = reopened.alarms.clear("link:modbus", "LINK_DOWN", at=T0 + timedelta(seconds=5))
        assert cleared is not None and not cleared.active
        assert cleared.cleared_at == T0 + timedelta(seconds=5)
        assert reopened.alarms.clear("link:modbus", "LINK_DOWN") is None  # nothing active
        # raised again after it cleared: a new alarm
        b, new4 = reopened.alarms.raise_("link:modbus", "LINK_DOWN", "high", "down again")
        assert new4 and b.id != a.id
        assert [k for _, k, _ in reopened.alarms.events(a.id)] == ["raised", "cleared"]
    finally:
        reopened.close()


def test_acknowledge_keeps_the_first_and_is_recorded(store: Store) -> None:
    a, _ = store.alarms.raise_("camera:left1", "CAMERA_RECONNECTED", "low", "camera left1 "
                               "reconnected", at=T0)
    acked, done = store.alarms.acknowledge(a.id, "alice", at=T0 + timedelta(minutes=1))
    assert done and acked.acked_by == "alice" and acked.acked_at == T0 + timedelta(minutes=1)
    again, done2 = store.alarms.acknowledge(a.id, "bob")
    assert not done2 and again.acked_by == "alice"
    assert store.alarms.events(a.id) == [(T0, "raised", None),
                                         (T0 + timedelta(minutes=1), "acknowledged", "alice")]
    with pytest.raises(NotFoundError, match="alarm 999999 not found"):
        store.alarms.acknowledge(999999, "alice")
    # another station's alarm is not this one's to acknowledge
    other = Store(store.engine, "station2")
    with pytest.raises(NotFoundError):
        other.alarms.acknowledge(a.id, "mallory")


def test_filters_counts_and_standing(store: Store) -> None:
    link, _ = store.alarms.raise_("link:modbus", "LINK_DOWN", "high", "t", at=T0)
    cam, _ = store.alarms.raise_("camera:left1", "CAMERA_RECONNECTED", "low", "t",
                                 at=T0 + timedelta(hours=1))
    drift, _ = store.alarms.raise_("drift:left1", "DRIFT_WARNING", "medium", "t",
                                   at=T0 + timedelta(hours=2))
    store.alarms.clear("camera:left1", "CAMERA_RECONNECTED")
    store.alarms.acknowledge(drift.id, "alice")

    def ids(**kw: object) -> list[int]:
        return [a.id for a in store.alarms.find(AlarmFilter(**kw))]  # type: ignore[arg-type]

    assert ids() == [drift.id, cam.id, link.id]
    assert ids(active=True) == [drift.id, link.id]
    assert ids(active=False) == [cam.id]
    assert ids(acknowledged=True) == [drift.id]
    assert ids(acknowledged=False) == [cam.id, link.id]
    assert ids(source="link:") == [link.id]
    assert ids(source="camera:left1") == [cam.id]
    assert ids(source="link") == []  # exact unless it ends in ':'
    assert ids(priority="medium") == [drift.id]
    assert ids(since=T0 + timedelta(minutes=30)) == [drift.id, cam.id]
    assert ids(until=T0 + timedelta(minutes=30)) == [link.id]
    assert ids(before_id=drift.id) == [cam.id, link.id]
    # standing: active, or cleared and not acknowledged
    assert [a.id for a in store.alarms.standing()] == [drift.id, cam.id, link.id]
    c = store.alarms.counts()
    assert (c.active, c.unacknowledged, c.highest) == (2, 2, "high")
    store.alarms.acknowledge(cam.id, "alice")
    assert [a.id for a in store.alarms.standing()] == [drift.id, link.id]


def test_transitions_queue_mqtt_messages_and_the_events_are_append_only(store: Store) -> None:
    store.alarms.topic = "acme/plant/body/l1/station1/mvpose/alarms"
    a, _ = store.alarms.raise_("store", "STORE_DOWN", "high", "the database is down", at=T0)
    store.alarms.raise_("store", "STORE_DOWN", "high", "again")  # idempotent: no message
    store.alarms.acknowledge(a.id, "alice")
    store.alarms.clear("store", "STORE_DOWN")
    pending = Outbox(store.engine, "station1").pending()
    assert [p.topic for p in pending] == [store.alarms.topic] * 3
    payloads = [json.loads(p.payload) for p in pending]
    assert [p["event"] for p in payloads] == ["raised", "acknowledged", "cleared"]
    assert [p["event_id"] for p in payloads] == [p.seq for p in pending]
    assert payloads[1]["by"] == "alice" and payloads[1]["alarm"]["acked_by"] == "alice"
    assert payloads[0]["schema"] == "mvpose.alarm/1"
    assert payloads[2]["alarm"]["cleared_at"] is not None
    with pytest.raises(Exception, match="append-only"), store.engine.begin() as conn:
        conn.execute(text("DELETE FROM alarm_events"))
