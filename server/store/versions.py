"""Versioned recipes and calibrations: every upload is a new version; one version is active."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any, Literal, cast

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Engine, Table, func, insert, select, update

from server.errors import InvalidInputError, NotFoundError
from server.store.chain import canonical_json, sha256_text
from server.store.models import ActiveVersionRow, VersionRow

Kind = Literal["recipe", "calibration"]
V = cast(Table, VersionRow.__table__)
A = cast(Table, ActiveVersionRow.__table__)


class VersionInfo(BaseModel):
    model_config = ConfigDict(frozen=True)

    kind: Kind
    name: str
    version: int
    sha256: str
    created_at: datetime
    created_by: str
    comment: str
    active: bool


class VersionSummary(BaseModel):
    model_config = ConfigDict(frozen=True)

    kind: Kind
    name: str
    latest_version: int
    active_version: int | None


class VersionRepository:
    """Queries on config_versions and active_versions for one station."""

    def __init__(self, engine: Engine, station: str) -> None:
        self._engine = engine
        self.station = station

    def add(
        self, kind: Kind, name: str, content: dict[str, Any], created_by: str, comment: str = ""
    ) -> VersionInfo:
        """Store ``content`` as the next version of ``name`` (versions count from 1)."""
        try:
            text = canonical_json(content)
        except ValueError as err:  # NaN / Infinity parsed from a lenient JSON body
            raise InvalidInputError(f"{kind} {name!r}: content is not plain JSON ({err})") from None
        with self._engine.begin() as conn:
            latest = conn.execute(
                select(func.max(V.c.version)).where(*self._key(kind, name))
            ).scalar_one_or_none()
            version = (latest or 0) + 1
            conn.execute(
                insert(V).values(
                    station=self.station,
                    kind=kind,
                    name=name,
                    version=version,
                    content=text,
                    sha256=sha256_text(text),
                    created_at=datetime.now(UTC),
                    created_by=created_by,
                    comment=comment[:400],
                )
            )
            return self._info(conn, kind, name, version)

    def find(self, kind: Kind, name: str, content: dict[str, Any]) -> VersionInfo | None:
        """The newest stored version with exactly this content, if any."""
        digest = sha256_text(canonical_json(content))
        with self._engine.connect() as conn:
            same = conn.execute(
                select(V.c.version)
                .where(*self._key(kind, name), V.c.sha256 == digest)
                .order_by(V.c.version.desc())
                .limit(1)
            ).scalar_one_or_none()
            return None if same is None else self._info(conn, kind, name, same)

    def activate(self, kind: Kind, name: str, version: int, by: str) -> VersionInfo:
        with self._engine.begin() as conn:
            row = conn.execute(
                select(V.c.id).where(*self._key(kind, name), V.c.version == version)
            ).first()
            if row is None:
                raise NotFoundError(f"{kind} {name!r} has no version {version}")
            values = {"version_id": row.id, "activated_at": datetime.now(UTC), "activated_by": by}
            key = (A.c.station == self.station, A.c.kind == kind, A.c.name == name)
            if conn.execute(update(A).where(*key).values(**values)).rowcount == 0:
                conn.execute(insert(A).values(station=self.station, kind=kind, name=name, **values))
            return self._info(conn, kind, name, version)

    def names(self, kind: Kind) -> list[VersionSummary]:
        with self._engine.connect() as conn:
            rows = conn.execute(
                select(V.c.name, func.max(V.c.version).label("latest"))
                .where(V.c.station == self.station, V.c.kind == kind)
                .group_by(V.c.name)
                .order_by(V.c.name)
            ).all()
            active = {
                r.name: r.version
                for r in conn.execute(
                    select(A.c.name, V.c.version)
                    .join(V, V.c.id == A.c.version_id)
                    .where(A.c.station == self.station, A.c.kind == kind)
                )
            }
        return [
            VersionSummary(
                kind=kind, name=r.name, latest_version=r.latest, active_version=active.get(r.name)
            )
            for r in rows
        ]

    def versions(self, kind: Kind, name: str) -> list[VersionInfo]:
        with self._engine.connect() as conn:
            numbers = (
                conn.execute(
                    select(V.c.version).where(*self._key(kind, name)).order_by(V.c.version)
                )
                .scalars()
                .all()
            )
            if not numbers:
                raise NotFoundError(f"{kind} {name!r} does not exist at station {self.station!r}")
            return [self._info(conn, kind, name, v) for v in numbers]

    def content(
        self, kind: Kind, name: str, version: int | None = None
    ) -> tuple[VersionInfo, dict[str, Any]]:
        """A version's content; ``version=None`` is the active one."""
        with self._engine.connect() as conn:
            if version is None:
                version = self._active_version(conn, kind, name)
                if version is None:
                    raise NotFoundError(f"{kind} {name!r} has no active version")
            row = conn.execute(
                select(V.c.content).where(*self._key(kind, name), V.c.version == version)
            ).first()
            if row is None:
                raise NotFoundError(f"{kind} {name!r} has no version {version}")
            return self._info(conn, kind, name, version), json.loads(row.content)

    # ------------------------------------------------------------------ helpers
    def _key(self, kind: Kind, name: str) -> tuple[Any, ...]:
        return (V.c.station == self.station, V.c.kind == kind, V.c.name == name)

    def _active_version(self, conn: Any, kind: Kind, name: str) -> int | None:
        return conn.execute(
            select(V.c.version)
            .join(A, A.c.version_id == V.c.id)
            .where(A.c.station == self.station, A.c.kind == kind, A.c.name == name)
        ).scalar_one_or_none()

    def _info(self, conn: Any, kind: Kind, name: str, version: int) -> VersionInfo:
        r = conn.execute(select(V).where(*self._key(kind, name), V.c.version == version)).one()
        return VersionInfo(
            kind=kind,
            name=name,
            version=r.version,
            sha256=r.sha256,
            created_at=r.created_at,
            created_by=r.created_by,
            comment=r.comment,
            active=self._active_version(conn, kind, name) == r.version,
        )
