"""Token repository: tokens are looked up by the sha256 of their secret, never stored in clear."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import cast

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Engine, Table, insert, select, update
from sqlalchemy.exc import IntegrityError

from server.errors import ConflictError, NotFoundError
from server.store.models import TokenRow

T = cast(Table, TokenRow.__table__)


class TokenInfo(BaseModel):
    model_config = ConfigDict(frozen=True)

    id: int
    name: str
    role: str
    created_at: datetime
    revoked_at: datetime | None


class TokenRepository:
    def __init__(self, engine: Engine) -> None:
        self._engine = engine

    def create(self, name: str, role: str, token_sha256: str) -> TokenInfo:
        try:
            with self._engine.begin() as conn:
                conn.execute(
                    insert(T).values(
                        name=name,
                        role=role,
                        token_sha256=token_sha256,
                        created_at=datetime.now(UTC),
                    )
                )
        except IntegrityError:
            raise ConflictError(
                f"a token named {name!r} (or with the same secret) exists"
            ) from None
        return self.by_name(name)

    def by_name(self, name: str) -> TokenInfo:
        with self._engine.connect() as conn:
            row = conn.execute(select(T).where(T.c.name == name)).first()
        if row is None:
            raise NotFoundError(f"token {name!r} does not exist")
        return _info(row)

    def by_hash(self, token_sha256: str) -> TokenInfo | None:
        """The live token with this hash (None when unknown or revoked)."""
        with self._engine.connect() as conn:
            row = conn.execute(
                select(T).where(T.c.token_sha256 == token_sha256, T.c.revoked_at.is_(None))
            ).first()
        return _info(row) if row else None

    def list(self) -> list[TokenInfo]:
        with self._engine.connect() as conn:
            return [_info(r) for r in conn.execute(select(T).order_by(T.c.id)).all()]

    def revoke(self, name: str) -> TokenInfo:
        with self._engine.begin() as conn:
            n = conn.execute(
                update(T)
                .where(T.c.name == name, T.c.revoked_at.is_(None))
                .values(revoked_at=datetime.now(UTC))
            ).rowcount
        if n == 0:
            raise NotFoundError(f"no live token named {name!r}")
        return self.by_name(name)

    def upsert_secret(self, name: str, role: str, token_sha256: str) -> TokenInfo:
        """Make ``name`` a live token with this secret and role (bootstrap token at start-up)."""
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
