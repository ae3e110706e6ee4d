"""The outbox: messages to publish, written in the transaction that inserts their measurement.

The durable writer's database thread inserts each sealed link together with its outbox rows
(:func:`result_rows`, given to ``DurableWriter.open(outbox=...)``), so a record is in the database
exactly when its message is queued: a broker that is down, a station that restarts or a database
that was down while the journal took the record lose nothing. The publisher
(server/station/mqtt.py) reads the unpublished rows in id order (:meth:`Outbox.pending`), publishes
them and marks them published once the broker acknowledged them (:meth:`Outbox.mark_published`).
Delivery is at least once: a row published but not yet marked when the connection or the station
dies is published again, with the same payload; consumers deduplicate (docs/integration.md).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any, cast

from sqlalchemy import Engine, Table, delete, func, select, update

from server.store.events import record_event
from server.store.measurements import Link, OutboxRows
from server.store.models import OutboxRow

O = cast(Table, OutboxRow.__table__)  # noqa: E741

SCHEMA = "mvpose.result/1"


def result_payload(link: Link, measurement_id: int) -> dict[str, Any]:
    """The result message of one record: every field of its result event, its ids and its
    place in the chain. Keys older than the event keep their shape: ``offset`` and
    ``calibration`` are objects, ``message`` is null when the record has none
    (docs/integration.md)."""
    rec = link.record
    event = record_event(rec, link.seq, stored_at=link.stored_at, hash=link.hash)
    return {
        "schema": SCHEMA,
        **event.to_dict(),
        "id": measurement_id,
        "station": link.station,
        "seq": link.seq,
        "prev_hash": link.prev_hash,
        "calibration": None if event.calibration_id is None else {
            "id": event.calibration_id, "sha256": event.calibration_sha256},
        "message": rec.message,
        "offset": None if event.offset is None else {
            "convention": event.convention, "values": list(event.offset)},
    }


def result_rows(topic: str) -> OutboxRows:
    """The writer's outbox hook: one row per record, to be published on ``topic``."""

    def rows(link: Link, measurement_id: int) -> list[dict[str, Any]]:
        payload = json.dumps(result_payload(link, measurement_id), separators=(",", ":"),
                             allow_nan=False)
        return [{"station": link.station, "seq": link.seq, "measurement_id": measurement_id,
                 "topic": topic, "payload": payload, "created_at": datetime.now(UTC),
                 "published_at": None}]

    return rows


@dataclass(frozen=True)
class Pending:
    """One outbox row to publish."""

    id: int
    seq: int
    topic: str
    payload: str


class Outbox:
    """The outbox rows of one station."""

    def __init__(self, engine: Engine, station: str) -> None:
        self.engine = engine
        self.station = station

    def pending(self, after_id: int = 0, limit: int = 100) -> list[Pending]:
        """Unpublished rows with an id above ``after_id``, oldest first."""
        with self.engine.connect() as conn:
            rows = conn.execute(
                select(O.c.id, O.c.seq, O.c.topic, O.c.payload)
                .where(O.c.station == self.station, O.c.published_at.is_(None),
                       O.c.id > after_id)
                .order_by(O.c.id).limit(limit)).all()
        return [Pending(r.id, r.seq, r.topic, r.payload) for r in rows]

    def mark_published(self, ids: Sequence[int], at: datetime | None = None) -> None:
        if not ids:
            return
        with self.engine.begin() as conn:
            conn.execute(update(O).where(O.c.id.in_(list(ids)), O.c.published_at.is_(None))
                         .values(published_at=at or datetime.now(UTC)))

    def unpublished(self) -> int:
        with self.engine.connect() as conn:
            return int(conn.execute(
                select(func.count()).select_from(O)
                .where(O.c.station == self.station, O.c.published_at.is_(None))).scalar_one())

    def prune(self, keep: timedelta) -> int:
        """Delete this station's rows published more than ``keep`` ago; how many."""
        with self.engine.begin() as conn:
            done = conn.execute(delete(O).where(
                O.c.station == self.station, O.c.published_at.is_not(None),
                O.c.published_at < datetime.now(UTC) - keep))
        return int(done.rowcount or 0)
