"""Shifts: the station file's list of shift start times in the plant's time zone, and which
shift a moment falls in (the line view's counters reset at each start)."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime, time, timedelta
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

from pydantic import BaseModel, ConfigDict, Field


class Shift(BaseModel):
    """One shift: its name and the wall-clock time it starts at; it ends where the next starts."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(pattern=r"^[A-Za-z0-9_. \-]+$", min_length=1, max_length=32)
    start: str = Field(pattern=r"^([01]\d|2[0-3]):[0-5]\d$", description="HH:MM, plant time")

    @property
    def start_time(self) -> time:
        h, m = self.start.split(":")
        return time(int(h), int(m))


#: three 8-hour shifts from 06:00 (the station file's default)
DEFAULT_SHIFTS = (Shift(name="early", start="06:00"), Shift(name="late", start="14:00"),
                  Shift(name="night", start="22:00"))


def time_zone(name: str) -> ZoneInfo:
    """The IANA zone ``name`` (``Europe/Berlin``, ``UTC``); ValueError naming it otherwise."""
    try:
        return ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        raise ValueError(f"time_zone {name!r} is not an IANA time zone (e.g. Europe/Berlin, "
                         "UTC)") from None


def check_shifts(shifts: list[Shift] | tuple[Shift, ...]) -> None:
    """At least one shift; names and start times unique."""
    if not shifts:
        raise ValueError("shifts: give at least one shift (name, start HH:MM)")
    for what, values in (("name", [s.name for s in shifts]), ("start", [s.start for s in shifts])):
        dup = sorted({v for v in values if values.count(v) > 1})
        if dup:
            raise ValueError(f"shifts: {what} {dup[0]!r} is given twice")


@dataclass(frozen=True)
class ShiftWindow:
    """The shift a moment falls in: its name and its start and end, aware UTC datetimes."""

    name: str
    start: datetime
    end: datetime


def shift_at(shifts: list[Shift] | tuple[Shift, ...], zone: ZoneInfo,
             now: datetime) -> ShiftWindow:
    """The shift ``now`` (aware) falls in: the latest start at or before it, up to the next."""
    if now.tzinfo is None:
        raise ValueError(f"shift_at: {now.isoformat()} has no time zone")
    local = now.astimezone(zone)
    starts = sorted(
        (datetime.combine(local.date() + timedelta(days=d), s.start_time, zone).astimezone(UTC),
         s.name)
        for d in (-1, 0, 1) for s in shifts)
    k = max(i for i, (t, _) in enumerate(starts) if t <= now)
    return ShiftWindow(starts[k][1], starts[k][0], starts[k + 1][0])
