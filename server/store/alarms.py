"""Alarms in the store: raise (idempotent per source and code while active), clear, acknowledge.

Each alarm is a row of ``alarms`` (when it was raised and cleared, who acknowledged it and when);
each transition is a row of the append-only ``alarm_events``, the alarms' audit trail. With a
``topic`` (the station's ``.../alarms`` MQTT topic, server/state.py sets it when the station
file has a ``plant.mqtt`` block), every transition also writes its outbox row in the same
transaction, so the station's publisher sends it exactly as it sends results (docs/alarms.md).

The vocabulary is ISA-18.2 / IEC 62682's: an alarm is *active* until its condition ends
(*cleared*), and *unacknowledged* until an operator acknowledges it; either may come first.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, Literal, cast

from pydantic import BaseModel, Field, computed_field
from sqlalchemy import Connection, Engine, Table, func, insert, select, update
from sqlalchemy.exc import IntegrityError

from server.errors import NotFoundError
from server.store.models import AlarmEventRow, AlarmRow, OutboxRow

A = cast(Table, AlarmRow.__table__)
E = cast(Table, AlarmEventRow.__table__)
O = cast(Table, OutboxRow.__table__)  # noqa: E741

SCHEMA = "mvpose.alarm/1"
Priority = Literal["high", "medium", "low"]
EventKind = Literal["raised", "acknowledged", "cleared"]


class Alarm(BaseModel):
    """One alarm as the store keeps it and REST, MQTT and the page show it."""

    id: int
    station: str
    source: str = Field(description="what raised it: station, store, link:<backend>, "
                        "camera:<id>, drift:<camera>, calibration, recipe:<name>")
    code: str = Field(description="what is wrong, e.g. LINK_DOWN (docs/alarms.md's table)")
    priority: Priority
    text: str = Field(description="the message in English")
    text_key: str = Field(description="the message's translation key (alarm.<code>)")
    text_args: dict[str, Any] = Field(description="the values the message names")
    raised_at: datetime
    cleared_at: datetime | None
    acked_at: datetime | None
    acked_by: str | None = Field(description="the user or token that acknowledged it")

    @computed_field(description="its condition holds (not cleared)")  # type: ignore[prop-decorator]
    @property
    def active(self) -> bool:
        return self.cleared_at is None

    @computed_field(description="an operator acknowledged it")  # type: ignore[prop-decorator]
    @property
    def acknowledged(self) -> bool:
        return self.acked_at is not None


@dataclass(frozen=True)
class AlarmFilter:
    """Which alarms a list shows; None: any."""

    standing: bool = False  # only the active or unacknowledged ones
    active: bool | None = None
    acknowledged: bool | None = None
    source: str | None = None  # exact, or a prefix ending in ':' (e.g. "link:")
    priority: Priority | None = None
    since: datetime | None = None  # raised at or after
    until: datetime | None = None  # raised before
    before_id: int | None = None  # paging: older than this alarm


@dataclass(frozen=True)
class AlarmCounts:
    """What the page header and the line view's banner show."""

    active: int
    unacknowledged: int
    highest: Priority | None  # of the active or unacknowledged ones


_PRIORITY_RANK = {"high": 3, "medium": 2, "low": 1}


class AlarmRepository:
    """The alarms of one station."""

    def __init__(self, engine: Engine, station: str, topic: str | None = None) -> None:
        self.engine = engine
        self.station = station
        self.topic = topic  # the MQTT topic of alarm messages, None: no outbox rows

    # ------------------------------------------------------------------ transitions
    def raise_(self, source: str, code: str, priority: Priority, text: str,
               args: dict[str, Any] | None = None, at: datetime | None = None
               ) -> tuple[Alarm, bool]:
        """Raise the alarm ``code`` of ``source``; while one is active, that one is returned
        unchanged. The bool says whether this call raised it."""
        at = at or datetime.now(UTC)
        values = {"station": self.station, "source": source, "code": code,
                  "priority": priority, "text": text[:400], "text_key": f"alarm.{code}",
                  "text_args": json.dumps(args or {}, separators=(",", ":"), default=str),
                  "raised_at": at, "cleared_at": None, "acked_at": None, "acked_by": None}
        try:
            with self.engine.begin() as conn:
                existing = self._active(conn, source, code)
                if existing is not None:
                    return existing, False
                done = conn.execute(insert(A).values(**values))
                alarm_id = int(done.inserted_primary_key[0])  # type: ignore[index]
                alarm = self._row(conn, alarm_id)
                self._event(conn, alarm, "raised", None, at)
                return alarm, True
        except IntegrityError:  # another process raised it between our look and our insert
            with self.engine.connect() as conn:
                existing = self._active(conn, source, code)
            if existing is None:
                raise
            return existing, False

    def clear(self, source: str, code: str, at: datetime | None = None) -> Alarm | None:
        """Clear the active alarm ``code`` of ``source``; None when none is active."""
        at = at or datetime.now(UTC)
        with self.engine.begin() as conn:
            existing = self._active(conn, source, code)
            if existing is None:
                return None
            conn.execute(update(A).where(A.c.id == existing.id).values(cleared_at=at))
            alarm = self._row(conn, existing.id)
            self._event(conn, alarm, "cleared", None, at)
            return alarm

    def acknowledge(self, alarm_id: int, by: str, at: datetime | None = None
                    ) -> tuple[Alarm, bool]:
        """Acknowledge alarm ``alarm_id`` as ``by``; an acknowledged one stays as it was (the
        first acknowledgement is kept). The bool says whether this call acknowledged it."""
        at = at or datetime.now(UTC)
        with self.engine.begin() as conn:
            done = conn.execute(update(A).where(
                A.c.id == alarm_id, A.c.station == self.station, A.c.acked_at.is_(None))
                .values(acked_at=at, acked_by=by[:64]))
            alarm = self._row(conn, alarm_id)
            if done.rowcount:
                self._event(conn, alarm, "acknowledged", by, at)
            return alarm, bool(done.rowcount)

    # ------------------------------------------------------------------ reading
    def get(self, alarm_id: int) -> Alarm:
        with self.engine.connect() as conn:
            return self._row(conn, alarm_id)

    def find(self, filters: AlarmFilter, limit: int = 100) -> list[Alarm]:
        """Matching alarms, newest first."""
        q = select(A).where(A.c.station == self.station)
        f = filters
        if f.standing:
            q = q.where(A.c.cleared_at.is_(None) | A.c.acked_at.is_(None))
        if f.active is not None:
            q = q.where(A.c.cleared_at.is_(None) if f.active else A.c.cleared_at.is_not(None))
        if f.acknowledged is not None:
            q = q.where(A.c.acked_at.is_not(None) if f.acknowledged else A.c.acked_at.is_(None))
        if f.source is not None:
            q = q.where(A.c.source.startswith(f.source, autoescape=True)
                        if f.source.endswith(":") else A.c.source == f.source)
        if f.priority is not None:
            q = q.where(A.c.priority == f.priority)
        if f.since is not None:
            q = q.where(A.c.raised_at >= f.since)
        if f.until is not None:
            q = q.where(A.c.raised_at < f.until)
        if f.before_id is not None:
            q = q.where(A.c.id < f.before_id)
        with self.engine.connect() as conn:
            rows = conn.execute(q.order_by(A.c.id.desc()).limit(limit)).all()
        return [_alarm(r) for r in rows]

    def standing(self) -> list[Alarm]:
        """The alarms an operator must see: active, or cleared and not yet acknowledged."""
        return self.find(AlarmFilter(standing=True), limit=1000)

    def counts(self) -> AlarmCounts:
        with self.engine.connect() as conn:
            rows = conn.execute(
                select(A.c.priority, A.c.cleared_at.is_(None).label("active"),
                       A.c.acked_at.is_(None).label("unacked"), func.count().label("n"))
                .where(A.c.station == self.station,
                       A.c.cleared_at.is_(None) | A.c.acked_at.is_(None))
                .group_by(A.c.priority, "active", "unacked")).all()
        active = sum(r.n for r in rows if r.active)
        unacked = sum(r.n for r in rows if r.unacked)
        highest = max((r.priority for r in rows), key=lambda p: _PRIORITY_RANK.get(p, 0),
                      default=None)
        return AlarmCounts(active, unacked, highest)

    def events(self, alarm_id: int) -> list[tuple[datetime, str, str | None]]:
        """The transitions of one alarm, oldest first: (at, kind, by)."""
        with self.engine.connect() as conn:
            rows = conn.execute(select(E.c.at, E.c.kind, E.c.by)
                                .where(E.c.alarm_id == alarm_id).order_by(E.c.id)).all()
        return [(r.at, r.kind, r.by) for r in rows]

    def transitions_after(self, after_id: int, limit: int = 200
                          ) -> list[tuple[int, EventKind, str | None, datetime, Alarm]]:
        """Transitions with an id above ``after_id``, oldest first: (event id, kind, by, at,
        the alarm as it is now)."""
        with self.engine.connect() as conn:
            rows = conn.execute(
                select(E.c.id.label("event_id"), E.c.kind, E.c.by, E.c.at, A)
                .join(A, A.c.id == E.c.alarm_id)
                .where(E.c.station == self.station, E.c.id > after_id)
                .order_by(E.c.id).limit(limit)).all()
        return [(r.event_id, r.kind, r.by, r.at, _alarm(r)) for r in rows]

    def last_transition(self) -> int:
        """The newest transition's id (0: none yet)."""
        with self.engine.connect() as conn:
            return int(conn.execute(select(func.coalesce(func.max(E.c.id), 0))
                                    .where(E.c.station == self.station)).scalar_one())

    # ------------------------------------------------------------------ inside a transaction
    def _active(self, conn: Connection, source: str, code: str) -> Alarm | None:
        row = conn.execute(select(A).where(
            A.c.station == self.station, A.c.source == source, A.c.code == code,
            A.c.cleared_at.is_(None))).first()
        return None if row is None else _alarm(row)

    def _row(self, conn: Connection, alarm_id: int) -> Alarm:
        row = conn.execute(select(A).where(A.c.id == alarm_id,
                                           A.c.station == self.station)).first()
        if row is None:
            raise NotFoundError(f"alarm {alarm_id} not found on station {self.station!r}")
        return _alarm(row)

    def _event(self, conn: Connection, alarm: Alarm, kind: EventKind, by: str | None,
               at: datetime) -> None:
        done = conn.execute(insert(E).values(
            station=self.station, alarm_id=alarm.id, at=at, kind=kind, by=by))
        event_id = int(done.inserted_primary_key[0])  # type: ignore[index]
        if self.topic is None:
            return
        payload = alarm_payload(alarm, kind, event_id, at, by)
        conn.execute(insert(O).values(
            station=self.station, seq=event_id, measurement_id=0, topic=self.topic,
            payload=json.dumps(payload, separators=(",", ":"), allow_nan=False),
            created_at=datetime.now(UTC), published_at=None))


def alarm_payload(alarm: Alarm, kind: EventKind, event_id: int, at: datetime,
                  by: str | None) -> dict[str, Any]:
    """The MQTT message of one transition (docs/alarms.md): the event and the alarm after it."""
    return {"schema": SCHEMA, "event": kind, "event_id": event_id, "at": at.isoformat(),
            "by": by, "alarm": alarm.model_dump(mode="json")}


def _alarm(row: Any) -> Alarm:
    return Alarm(id=row.id, station=row.station, source=row.source, code=row.code,
                 priority=row.priority, text=row.text, text_key=row.text_key,
                 text_args=json.loads(row.text_args), raised_at=row.raised_at,
                 cleared_at=row.cleared_at, acked_at=row.acked_at, acked_by=row.acked_by)
