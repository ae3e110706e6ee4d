"""The line view's figures from the store: one shift's counts and cycle times, the NOKs in a row.

Read from the measurements table (so they survive a restart of either process), over the
``(station, triggered_at)`` and ``(station, id)`` indexes: cheap enough to ask every few seconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any, cast

from sqlalchemy import Engine, Float, Table, func, select
from sqlalchemy import cast as sql_cast
from sqlalchemy.dialects.postgresql import JSONB

from server.store.measurements import _aware
from server.store.models import MeasurementRow

M = cast(Table, MeasurementRow.__table__)


@dataclass(frozen=True)
class ShiftCounts:
    """Results triggered in ``[since, until)``; cycle times (``timings_ms.total``) in ms over
    every result that has one, None when there is none."""

    ok: int
    nok: int
    min_ms: float | None
    mean_ms: float | None
    max_ms: float | None

    @property
    def total(self) -> int:
        return self.ok + self.nok

    @property
    def yield_pct(self) -> float | None:
        return 100.0 * self.ok / self.total if self.total else None


class ShiftRepository:
    def __init__(self, engine: Engine, station: str) -> None:
        self._engine = engine
        self.station = station

    def _total_ms(self) -> Any:
        # The cycle time is in the hashed JSON body (no column of its own): read in SQL.
        if self._engine.dialect.name == "postgresql":
            return sql_cast(sql_cast(M.c.body, JSONB)[("record", "timings_ms", "total")].astext,
                            Float)
        return func.json_extract(M.c.body, "$.record.timings_ms.total")

    def counts(self, since: datetime, until: datetime) -> ShiftCounts:
        """OK and NOK counts and min/mean/max cycle time of the results triggered in
        ``[since, until)``."""
        total = self._total_ms()
        q = (select(M.c.result, func.count(), func.min(total), func.avg(total), func.max(total))
             .where(M.c.station == self.station,
                    M.c.triggered_at >= _aware(since, "since"),
                    M.c.triggered_at < _aware(until, "until"))
             .group_by(M.c.result))
        with self._engine.connect() as conn:
            rows = conn.execute(q).all()
        by = {r[0]: r for r in rows}
        ok, nok = by.get("OK"), by.get("NOK")
        mins = [float(r[2]) for r in rows if r[2] is not None]
        maxs = [float(r[4]) for r in rows if r[4] is not None]
        n = sum(int(r[1]) for r in rows if r[3] is not None)
        mean = (sum(float(r[3]) * int(r[1]) for r in rows if r[3] is not None) / n) if n else None
        return ShiftCounts(ok=int(ok[1]) if ok else 0, nok=int(nok[1]) if nok else 0,
                           min_ms=min(mins, default=None), mean_ms=mean,
                           max_ms=max(maxs, default=None))

    def nok_streak(self) -> int:
        """How many results in a row, newest first, are NOK (0 when the newest is OK)."""
        last_ok = (select(func.max(M.c.id))
                   .where(M.c.station == self.station, M.c.result == "OK").scalar_subquery())
        q = select(func.count()).select_from(M).where(
            M.c.station == self.station, M.c.id > func.coalesce(last_ok, 0))
        with self._engine.connect() as conn:
            return int(conn.execute(q).scalar_one())
