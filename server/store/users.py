"""User repository: the operator page's people, their hashed secrets, lockout counters and
their audit trail (``user_events``, append-only). The policy is in server/users.py."""

from __future__ import annotations

import builtins
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import cast

from pydantic import BaseModel, ConfigDict
from sqlalchemy import Connection, Engine, Table, insert, select, update
from sqlalchemy.exc import IntegrityError

from server.errors import ConflictError, NotFoundError
from server.store.models import UserEventRow, UserRow

U = cast(Table, UserRow.__table__)
E = cast(Table, UserEventRow.__table__)


class UserInfo(BaseModel):
    """A user as the API and the CLI show it (never the secret or its hash)."""

    model_config = ConfigDict(frozen=True)

    id: int
    name: str
    role: str
    secret_kind: str
    created_at: datetime
    disabled_at: datetime | None
    failed_count: int
    locked_at: datetime | None


class UserEvent(BaseModel):
    """One line of the users' audit trail."""

    model_config = ConfigDict(frozen=True)

    id: int
    at: datetime
    station: str
    user_name: str
    event: str
    actor: str
    detail: str


@dataclass(frozen=True)
class UserSecret:
    """What a login needs: the hash, the counters and the session epoch."""

    info: UserInfo
    secret_hash: str
    last_failed_at: datetime | None
    epoch: int


class UserRepository:
    """Users in the database. Every change writes its audit event in the same transaction."""

    def __init__(self, engine: Engine, station: str) -> None:
        self._engine = engine
        self._station = station

    def _event(self, conn: Connection, user: str, event: str, actor: str, detail: str,
               at: datetime | None = None) -> None:
        conn.execute(insert(E).values(at=at or datetime.now(UTC), station=self._station,
                                      user_name=user, event=event, actor=actor[:64],
                                      detail=detail))

    def create(self, name: str, role: str, kind: str, secret_hash: str, actor: str) -> UserInfo:
        """A new user; ConflictError when the name is taken (disabled users keep theirs)."""
        now = datetime.now(UTC)
        try:
            with self._engine.begin() as conn:
                conn.execute(insert(U).values(
                    name=name, role=role, secret_kind=kind, secret_hash=secret_hash,
                    created_at=now, failed_count=0, epoch=0))
                self._event(conn, name, "created", actor, f"role {role}, {kind}", now)
        except IntegrityError:
            raise ConflictError(f"a user named {name!r} exists (reset or enable it, or "
                                "choose another name)") from None
        return self.info(name)

    def secret(self, name: str) -> UserSecret | None:
        with self._engine.connect() as conn:
            row = conn.execute(select(U).where(U.c.name == name)).first()
        if row is None:
            return None
        return UserSecret(_info(row), row.secret_hash, row.last_failed_at, row.epoch)

    def info(self, name: str) -> UserInfo:
        found = self.secret(name)
        if found is None:
            raise NotFoundError(f"user {name!r} does not exist")
        return found.info

    def list(self) -> list[UserInfo]:
        with self._engine.connect() as conn:
            return [_info(r) for r in conn.execute(select(U).order_by(U.c.name)).all()]

    def _change(self, name: str, values: dict[str, object], event: str, actor: str,
                detail: str) -> UserInfo:
        with self._engine.begin() as conn:
            n = conn.execute(update(U).where(U.c.name == name).values(**values)).rowcount
            if n == 0:
                raise NotFoundError(f"user {name!r} does not exist")
            self._event(conn, name, event, actor, detail)
        return self.info(name)

    def set_role(self, name: str, role: str, actor: str) -> UserInfo:
        old = self.info(name).role
        return self._change(name, {"role": role}, "role", actor, f"role {old} -> {role}")

    def disable(self, name: str, actor: str) -> UserInfo:
        """Disabled: no login, and every open session of the user ends (the epoch moves)."""
        return self._change(name, {"disabled_at": datetime.now(UTC), "epoch": U.c.epoch + 1},
                            "disabled", actor, "")

    def enable(self, name: str, actor: str) -> UserInfo:
        return self._change(name, {"disabled_at": None}, "enabled", actor, "")

    def reset(self, name: str, kind: str, secret_hash: str, actor: str) -> UserInfo:
        """A new secret: the lock and the count of wrong secrets go, open sessions end."""
        return self._change(name, {"secret_kind": kind, "secret_hash": secret_hash,
                                   "failed_count": 0, "last_failed_at": None,
                                   "locked_at": None, "epoch": U.c.epoch + 1},
                            "reset", actor, f"new {kind}")

    def failed(self, name: str, lock_after: int, source: str,
               now: datetime | None = None) -> tuple[int, bool]:
        """One more wrong secret at ``now``, counted in the database (two panels at once both
        count); the user is locked when the count reaches ``lock_after``. Returns (count,
        locked)."""
        now = now or datetime.now(UTC)
        with self._engine.begin() as conn:
            conn.execute(update(U).where(U.c.name == name).values(
                failed_count=U.c.failed_count + 1, last_failed_at=now))
            row = conn.execute(select(U.c.failed_count, U.c.locked_at)
                               .where(U.c.name == name)).one()
            count, locked = int(row.failed_count), row.locked_at is not None
            self._event(conn, name, "login_failed", name, f"wrong secret {count} in a row "
                        f"from {source}", now)
            if count >= lock_after and not locked:
                conn.execute(update(U).where(U.c.name == name).values(locked_at=now))
                self._event(conn, name, "locked", name, f"{count} wrong secrets in a row; "
                            "an engineer resets the user", now)
                locked = True
        return count, locked

    def logged_in(self, name: str, source: str) -> None:
        with self._engine.begin() as conn:
            conn.execute(update(U).where(U.c.name == name).values(failed_count=0,
                                                                  last_failed_at=None))
            self._event(conn, name, "login", name, f"from {source}")

    def refused(self, name: str, why: str, source: str) -> None:
        """A login refused before its secret was checked (locked, waiting, disabled)."""
        with self._engine.begin() as conn:
            self._event(conn, name, "login_refused", name, f"{why} (from {source})")

    def events(self, user: str | None = None, limit: int = 100,
               before_id: int | None = None) -> builtins.list[UserEvent]:
        """The audit trail, newest first."""
        q = select(E).order_by(E.c.id.desc()).limit(limit)
        if user is not None:
            q = q.where(E.c.user_name == user)
        if before_id is not None:
            q = q.where(E.c.id < before_id)
        with self._engine.connect() as conn:
            return [UserEvent.model_validate(r, from_attributes=True)
                    for r in conn.execute(q).all()]


def _info(row: object) -> UserInfo:
    return UserInfo.model_validate(row, from_attributes=True)
