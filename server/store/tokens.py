"""Token repository: tokens are looked up by the sha256 of their secret, never stored in clear."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from typing import cast

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Engine, Table, func, insert, select, update
from sqlalchemy.exc import IntegrityError

from server.errors import ConflictError, NotFoundError
from server.store.models import TokenRow

T = cast(Table, TokenRow.__table__)

#: the role that manages tokens; its last live token cannot be revoked
ENGINEER = "engineer"


class TokenInfo(BaseModel):
    model_config = ConfigDict(frozen=True)

    id: int
    name: str
    role: str
    created_at: datetime
    revoked_at: datetime | None


#: how long a verified token is trusted without asking the database again (s)
VERIFIED_TTL_S = 2.0


class TokenRepository:
    """Tokens in the database, with the live tokens verified in the last ``verified_ttl_s``
    remembered (:meth:`recent`): MES clients poll with the same token many times a second.

    A revoke or upsert through this repository forgets them all at once; a change made
    by another process on the same database (another station's server on a shared PostgreSQL)
    takes effect here within ``verified_ttl_s``.
    """

    def __init__(
        self, engine: Engine, verified_ttl_s: float = VERIFIED_TTL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._engine = engine
        self._ttl = verified_ttl_s
        self._clock = clock
        self._verified: dict[str, tuple[float, TokenInfo]] = {}  # hash -> (expiry, info)
        self._generation = 0  # counts changes made here: a look-up older than one is not kept
        self._lock = threading.Lock()

    def recent(self, token_sha256: str) -> TokenInfo | None:
        """The live token with this hash if it was verified less than the TTL ago; None means
        "not known here": ask :meth:`by_hash` (a query)."""
        hit = self._verified.get(token_sha256)
        if hit is None or hit[0] <= self._clock():
            return None
        return hit[1]

    def _forget(self) -> None:
        with self._lock:
            self._verified.clear()
            self._generation += 1

    def create(self, name: str, role: str, token_sha256: str) -> TokenInfo:
        """A new live token. The name of a revoked token may be used again: its row takes the
        new secret, role and creation time (requests with the old secret stay refused)."""
        try:
            return self._create(name, role, token_sha256)
        finally:
            self._forget()

    def _create(self, name: str, role: str, token_sha256: str) -> TokenInfo:
        now = datetime.now(UTC)
        try:
            with self._engine.begin() as conn:
                reused = conn.execute(
                    update(T)
                    .where(T.c.name == name, T.c.revoked_at.is_not(None))
                    .values(role=role, token_sha256=token_sha256, created_at=now, revoked_at=None)
                ).rowcount
                if reused == 0:
                    conn.execute(
                        insert(T).values(
                            name=name, role=role, token_sha256=token_sha256, created_at=now
                        )
                    )
        except IntegrityError:
            raise ConflictError(
                f"a live token named {name!r} exists (revoke it first to reuse the name)"
            ) from None
        return self.by_name(name)

    def by_name(self, name: str) -> TokenInfo:
        with self._engine.connect() as conn:
            row = conn.execute(select(T).where(T.c.name == name)).first()
        if row is None:
            raise NotFoundError(f"token {name!r} does not exist")
        return _info(row)

    def by_hash(self, token_sha256: str) -> TokenInfo | None:
        """The live token with this hash (None when unknown or revoked), from the database."""
        expiry = self._clock() + self._ttl  # from before the query: a revoke after it counts
        generation = self._generation
        with self._engine.connect() as conn:
            row = conn.execute(
                select(T).where(T.c.token_sha256 == token_sha256, T.c.revoked_at.is_(None))
            ).first()
        if row is None:  # unknown or revoked: nothing remembered for it either
            with self._lock:
                self._verified.pop(token_sha256, None)
            return None
        info = _info(row)
        with self._lock:
            if generation != self._generation:  # a change here during the query: not kept
                return info
            if len(self._verified) > 1000:  # a bound, not a policy: stale entries go first
                now = self._clock()
                self._verified = {h: v for h, v in self._verified.items() if v[0] > now}
            self._verified[token_sha256] = (expiry, info)
        return info

    def live_count(self, role: str) -> int:
        """How many live (not revoked) tokens have this role."""
        with self._engine.connect() as conn:
            n = conn.execute(
                select(func.count()).select_from(T)
                .where(T.c.role == role, T.c.revoked_at.is_(None))
            ).scalar_one()
        return int(n)

    def list(self) -> list[TokenInfo]:
        with self._engine.connect() as conn:
            return [_info(r) for r in conn.execute(select(T).order_by(T.c.id)).all()]

    def revoke(self, name: str) -> TokenInfo:
        try:
            return self._revoke(name)
        finally:  # after the commit: a request verified meanwhile is not remembered past it
            self._forget()

    def _revoke(self, name: str) -> TokenInfo:
        live_engineers = select(func.count()).select_from(T).where(
            T.c.role == ENGINEER, T.c.revoked_at.is_(None)).scalar_subquery()
        with self._engine.begin() as conn:
            # PostgreSQL: lock the live engineer rows, so two revokes of the last two engineers
            # cannot both see the other one (SQLite runs one writer at a time anyway).
            conn.execute(select(T.c.id).where(T.c.role == ENGINEER, T.c.revoked_at.is_(None))
                         .with_for_update())
            n = conn.execute(
                update(T)
                .where(T.c.name == name, T.c.revoked_at.is_(None),
                       (T.c.role != ENGINEER) | (live_engineers > 1))
                .values(revoked_at=datetime.now(UTC))
            ).rowcount
        if n == 0:
            info = self._live(name)
            if info is None:
                raise NotFoundError(f"no live token named {name!r}")
            raise ConflictError(
                f"token {name!r} is the last live engineer token: revoking it would leave "
                "nobody able to manage tokens, recipes or calibrations; create another "
                "engineer token first (POST /api/v1/tokens or `mvpose token create`)"
            )
        return self.by_name(name)

    def _live(self, name: str) -> TokenInfo | None:
        with self._engine.connect() as conn:
            row = conn.execute(
                select(T).where(T.c.name == name, T.c.revoked_at.is_(None))).first()
        return None if row is None else _info(row)

    def upsert_secret(self, name: str, role: str, token_sha256: str) -> TokenInfo:
        """Make ``name`` a live token with this secret and role (bootstrap token at start-up)."""
        try:
            return self._upsert(name, role, token_sha256)
        finally:
            self._forget()

    def _upsert(self, name: str, role: str, token_sha256: str) -> TokenInfo:
        with self._engine.begin() as conn:
            n = conn.execute(
                update(T)
                .where(T.c.name == name)
                .values(role=role, token_sha256=token_sha256, revoked_at=None)
            ).rowcount
            if n == 0:
                conn.execute(
                    insert(T).values(
                        name=name,
                        role=role,
                        token_sha256=token_sha256,
                        created_at=datetime.now(UTC),
                    )
                )
        return self.by_name(name)


def _info(row: object) -> TokenInfo:
    return TokenInfo.model_validate(row, from_attributes=True)
