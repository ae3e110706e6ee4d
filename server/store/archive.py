"""Image-row repository: which archived frames exist, their sizes, and which to evict first."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime
from typing import cast

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Engine, Table, func, insert, select, update

from server.store.models import ImageRow, MeasurementRow

I = cast(Table, ImageRow.__table__)  # noqa: E741
M = cast(Table, MeasurementRow.__table__)


class ImageInfo(BaseModel):
    model_config = ConfigDict(frozen=True)

    id: int
    measurement_id: int
    view: int
    camera_id: str
    path: str
    bytes: int
    ok: bool
    created_at: datetime
    evicted_at: datetime | None


class ImageRepository:
    def __init__(self, engine: Engine, station: str) -> None:
        self._engine = engine
        self.station = station

    def add(
        self, measurement_id: int, view: int, camera_id: str, path: str, nbytes: int, ok: bool
    ) -> ImageInfo:
        with self._engine.begin() as conn:
            new_id = conn.execute(
                insert(I)
                .values(
                    measurement_id=measurement_id,
                    view=view,
                    camera_id=camera_id,
                    path=path,
                    bytes=nbytes,
                    ok=ok,
                    created_at=datetime.now(UTC),
                )
                .returning(I.c.id)
            ).scalar_one()
            return _info(conn.execute(select(I).where(I.c.id == new_id)).one())

    def for_measurement(self, measurement_id: int) -> list[ImageInfo]:
        with self._engine.connect() as conn:
            rows = conn.execute(
                select(I).where(I.c.measurement_id == measurement_id).order_by(I.c.id)
            ).all()
        return [_info(r) for r in rows]

    def stored_bytes(self) -> int:
        """Bytes of this station's frames still on disk."""
        with self._engine.connect() as conn:
            return int(
                conn.execute(
                    select(func.coalesce(func.sum(I.c.bytes), 0))
                    .select_from(I)
                    .join(M, M.c.id == I.c.measurement_id)
                    .where(I.c.evicted_at.is_(None), M.c.station == self.station)
                ).scalar_one()
            )

    def eviction_order(self, limit: int) -> list[ImageInfo]:
        """Frames on disk, OK frames first and oldest first within each group."""
        with self._engine.connect() as conn:
            rows = conn.execute(
                select(I)
                .join(M, M.c.id == I.c.measurement_id)
                .where(I.c.evicted_at.is_(None), M.c.station == self.station)
                .order_by(I.c.ok.desc(), I.c.id)
                .limit(limit)
            ).all()
        return [_info(r) for r in rows]

    def mark_evicted(self, ids: Sequence[int]) -> None:
        if not ids:
            return
        with self._engine.begin() as conn:
            conn.execute(
                update(I).where(I.c.id.in_(list(ids))).values(evicted_at=datetime.now(UTC))
            )


def _info(row: object) -> ImageInfo:
    return ImageInfo.model_validate(row, from_attributes=True)
