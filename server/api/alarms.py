"""Alarm endpoints: the list (standing, active, history, filtered), one alarm with its
transitions, the counts for a banner, and acknowledge (docs/alarms.md)."""

from __future__ import annotations

import logging
from datetime import datetime
from typing import Annotated, Literal

from fastapi import APIRouter, Path, Query
from fastapi.responses import Response
from pydantic import BaseModel, Field

from server.api.deps import IsoDateTime, OperatorUser, ReadUser, StoreDep, json_response
from server.errors import InvalidInputError
from server.store.alarms import Alarm, AlarmFilter, Priority
from server.store.schemas import MAX_ID

log = logging.getLogger(__name__)

router = APIRouter(prefix="/alarms", tags=["alarms"])

AlarmId = Annotated[int, Path(ge=1, le=MAX_ID)]


class AlarmEvent(BaseModel):
    at: datetime
    kind: Literal["raised", "acknowledged", "cleared"]
    by: str | None = Field(description="who acknowledged it")


class AlarmDetail(Alarm):
    events: list[AlarmEvent] = Field(description="its transitions, oldest first")


class AlarmPage(BaseModel):
    items: list[Alarm]
    next_before_id: int | None = Field(description="pass as before_id for the next page")


class AlarmSummary(BaseModel):
    active: int
    unacknowledged: int
    highest: Priority | None = Field(description="of the standing alarms")


def _aware(name: str, value: datetime | None) -> datetime | None:
    if value is not None and value.tzinfo is None:
        raise InvalidInputError(f"{name} {value.isoformat()} has no time zone; add Z or +01:00")
    return value


@router.get("", response_model=AlarmPage)
def list_alarms(
    _: ReadUser,
    store: StoreDep,
    standing: Annotated[bool, Query(
        description="only the alarms an operator must see: active, or not acknowledged")] = False,
    active: Annotated[bool | None, Query(description="true: active; false: cleared")] = None,
    acknowledged: bool | None = None,
    source: Annotated[str | None, Query(
        max_length=64, description="exact (camera:left1), or a prefix ending in ':' (link:)")
    ] = None,
    priority: Priority | None = None,
    since: Annotated[IsoDateTime | None, Query(
        description="raised at or after (ISO 8601, with zone)")] = None,
    until: Annotated[IsoDateTime | None, Query(
        description="raised before (ISO 8601, with zone)")] = None,
    before_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> Response:
    """Alarms, newest first: the history, filtered; pass next_before_id for the next page."""
    filters = AlarmFilter(standing=standing, active=active, acknowledged=acknowledged,
                          source=source, priority=priority, since=_aware("since", since),
                          until=_aware("until", until), before_id=before_id)
    items = store.alarms.find(filters, limit + 1)
    more = items[limit - 1].id if len(items) > limit else None
    items = items[:limit]
    return json_response(AlarmPage(items=items, next_before_id=more))


@router.get("/summary", response_model=AlarmSummary)
def alarm_summary(_: ReadUser, store: StoreDep) -> Response:
    """How many alarms are active and unacknowledged, and the highest priority among them."""
    c = store.alarms.counts()
    return json_response(AlarmSummary(active=c.active, unacknowledged=c.unacknowledged,
                                      highest=c.highest))


@router.get("/{alarm_id}", response_model=AlarmDetail)
def get_alarm(_: ReadUser, store: StoreDep, alarm_id: AlarmId) -> Response:
    """One alarm with its transitions (raised, acknowledged, cleared) and who acknowledged it."""
    alarm = store.alarms.get(alarm_id)
    events = [AlarmEvent(at=at, kind=kind, by=by)
              for at, kind, by in store.alarms.events(alarm_id)]
    return json_response(AlarmDetail(**alarm.model_dump(exclude={"active", "acknowledged"}),
                                     events=events))


@router.post("/{alarm_id}/acknowledge", response_model=Alarm)
def acknowledge_alarm(user: OperatorUser, store: StoreDep, alarm_id: AlarmId) -> Response:
    """Acknowledge an alarm (operator or engineer); the first acknowledgement is kept."""
    alarm, done = store.alarms.acknowledge(alarm_id, user.name)
    if done:
        log.info("alarm %d (%s %s) acknowledged by %s", alarm.id, alarm.source, alarm.code,
                 user.name)
    return json_response(alarm)
