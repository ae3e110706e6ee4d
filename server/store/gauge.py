"""Gauge studies in the audit trail: each study's canonical JSON sealed as the next link of the
station's chain of studies (sha256 over the previous hash and the body, as measurements are)."""

from __future__ import annotations

import json
from datetime import UTC, datetime
from typing import Any, cast

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Engine, Table, insert, select
from sqlalchemy.exc import IntegrityError

from server.errors import ConflictError, InvalidInputError, NotFoundError
from server.store.chain import GENESIS, canonical_json, seal
from server.store.models import GaugeStudyRow

G = cast(Table, GaugeStudyRow.__table__)


class StoredStudy(BaseModel):
    """A stored study: its place in the chain and its body (the study and its figures)."""

    model_config = ConfigDict(frozen=True)

    id: int
    seq: int
    kind: str
    recipe: str
    created_at: datetime
    created_by: str
    passed: bool
    prev_hash: str
    hash: str
    body: dict[str, Any]


class GaugeStudyRepository:
    """Queries on gauge_studies for one station."""

    def __init__(self, engine: Engine, station: str) -> None:
        self._engine = engine
        self.station = station

    def add(self, body: dict[str, Any], created_by: str) -> StoredStudy:
        """Seal ``body`` (with who and when) as the station's next study."""
        now = datetime.now(UTC)
        envelope = {"station": self.station, "created_at": now.isoformat(),
                    "created_by": created_by, "study": body}
        try:
            text = canonical_json(envelope)
        except ValueError as err:
            raise InvalidInputError(f"gauge study: not plain JSON ({err})") from None
        for _ in range(3):  # two writers racing for the same seq: the loser tries again
            try:
                with self._engine.begin() as conn:
                    head = conn.execute(
                        select(G.c.seq, G.c.hash).where(G.c.station == self.station)
                        .order_by(G.c.seq.desc()).limit(1)
                    ).first()
                    seq, prev = (head.seq + 1, head.hash) if head else (1, GENESIS)
                    result = conn.execute(insert(G).values(
                        station=self.station, seq=seq, kind=body["kind"], recipe=body["recipe"],
                        created_at=now, created_by=created_by[:64], passed=bool(body["passed"]),
                        body=text, prev_hash=prev, hash=seal(prev, text),
                    ))
                    new_id = int(cast(Any, result.inserted_primary_key)[0])
            except IntegrityError:
                continue
            return self.get(new_id)
        raise ConflictError("gauge study: the chain's head kept moving; try again")

    def get(self, study_id: int) -> StoredStudy:
        with self._engine.connect() as conn:
            r = conn.execute(
                select(G).where(G.c.station == self.station, G.c.id == study_id)
            ).first()
        if r is None:
            raise NotFoundError(f"gauge study {study_id} does not exist at station "
                                f"{self.station!r}")
        return _stored(r)

    def newest(self, limit: int = 100) -> list[StoredStudy]:
        """The newest studies first."""
        with self._engine.connect() as conn:
            rows = conn.execute(
                select(G).where(G.c.station == self.station).order_by(G.c.seq.desc())
                .limit(limit)
            ).all()
        return [_stored(r) for r in rows]

    def verify(self) -> list[str]:
        """Problems of the chain of studies (empty: every link is intact)."""
        problems = []
        prev = GENESIS
        with self._engine.connect() as conn:
            rows = conn.execute(
                select(G).where(G.c.station == self.station).order_by(G.c.seq)
            ).all()
        for r in rows:
            if r.prev_hash != prev:
                problems.append(f"study seq {r.seq}: prev_hash does not match seq {r.seq - 1}")
            if seal(r.prev_hash, r.body) != r.hash:
                problems.append(f"study seq {r.seq}: hash does not match its body")
            prev = r.hash
        return problems


def _stored(r: Any) -> StoredStudy:
    envelope = json.loads(r.body)
    return StoredStudy(id=r.id, seq=r.seq, kind=r.kind, recipe=r.recipe,
                       created_at=r.created_at, created_by=r.created_by, passed=r.passed,
                       prev_hash=r.prev_hash, hash=r.hash, body=envelope["study"])
