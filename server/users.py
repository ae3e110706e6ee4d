"""People on the operator page: a PIN (operators at a panel PC) or a password (engineers),
each with a role; hashing, the lockout after wrong secrets, and the session check.

Secrets are stored as scrypt hashes (``hashlib.scrypt``, memory-hard: N=2^14, r=8, p=1, 16 MiB
and some 50 ms a check) with a random 16-byte salt per user, and compared in constant time.
A PIN has little entropy (4 digits: 10,000 values), so the number of guesses is what protects
it, not the hash: after :data:`FREE_TRIES` wrong secrets in a row each further try waits
(:func:`wait_s`, doubling from :data:`FIRST_WAIT_S`), and the :data:`LOCK_AFTER`-th locks the
user until an engineer resets it. A guesser thus gets 10 tries in all: one chance in 1,000
against a 4-digit PIN, one in 100,000 against a 6-digit one. Every login, wrong secret, refusal
and lock is in the users' audit trail (server/store/users.py).
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import StrEnum

from server.auth import Principal, Role
from server.errors import (
    ForbiddenError,
    InvalidInputError,
    TooManyAttemptsError,
    UnauthenticatedError,
)
from server.store.users import UserInfo, UserRepository

#: scrypt's cost: N (CPU and memory), r (block size), p (parallelism); 128·N·r = 16 MiB
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
SALT_BYTES, KEY_BYTES = 16, 32
#: wrong secrets in a row that cost nothing but a retry
FREE_TRIES = 5
#: the wait after the FREE_TRIES-th wrong secret; it doubles with each further one
FIRST_WAIT_S = 30.0
#: the wrong secret in a row that locks the user until an engineer resets it
LOCK_AFTER = 10
PIN_PATTERN = re.compile(r"^[0-9]{4,8}$")
PASSWORD_MIN, PASSWORD_MAX = 10, 200
NAME_PATTERN = r"^[A-Za-z0-9_.\-]+$"


class SecretKind(StrEnum):
    """How a user logs in: a PIN (4 to 8 digits) or a password (10 characters or more)."""

    PIN = "pin"
    PASSWORD = "password"


def check_secret(kind: SecretKind, secret: str) -> None:
    """InvalidInputError naming what is wrong with a new PIN or password (never the value)."""
    if kind is SecretKind.PIN:
        if not PIN_PATTERN.fullmatch(secret):
            raise InvalidInputError(f"a PIN has 4 to 8 digits, got {len(secret)} characters"
                                    + ("" if secret.isdigit() else " that are not all digits"))
    elif not PASSWORD_MIN <= len(secret) <= PASSWORD_MAX:
        raise InvalidInputError(f"a password has {PASSWORD_MIN} to {PASSWORD_MAX} characters, "
                                f"got {len(secret)}")


def _b64(raw: bytes) -> str:
    return base64.b64encode(raw).decode()


def hash_secret(secret: str, salt: bytes | None = None) -> str:
    """``scrypt$N$r$p$salt$key`` (base64): everything a later check needs."""
    salt = salt if salt is not None else secrets.token_bytes(SALT_BYTES)
    key = hashlib.scrypt(secret.encode(), salt=salt, n=SCRYPT_N, r=SCRYPT_R, p=SCRYPT_P,
                         dklen=KEY_BYTES)
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${_b64(salt)}${_b64(key)}"


def verify_secret(secret: str, stored: str) -> bool:
    """Whether ``secret`` gives the stored hash (its own cost and salt); constant-time compare."""
    try:
        scheme, n, r, p, salt, key = stored.split("$")
        if scheme != "scrypt":
            return False
        want = base64.b64decode(key)
        got = hashlib.scrypt(secret.encode(), salt=base64.b64decode(salt), n=int(n), r=int(r),
                             p=int(p), dklen=len(want), maxmem=256 * int(n) * int(r) + 2**20)
    except ValueError:
        return False
    return hmac.compare_digest(got, want)


# A hash to check unknown names against, so that they take as long as known ones.
_DUMMY = hash_secret("not a user", b"\0" * SALT_BYTES)


def wait_s(failed: int) -> float:
    """How long a user with ``failed`` wrong secrets in a row waits before the next try."""
    if failed < FREE_TRIES:
        return 0.0
    return FIRST_WAIT_S * 2 ** (failed - FREE_TRIES)


@dataclass(frozen=True)
class UserLogin:
    """A successful login: who, and the user's session epoch (a reset or disable moves it)."""

    principal: Principal
    epoch: int


def _word(kind: str) -> str:
    return "PIN" if kind == SecretKind.PIN else "password"


def login(repo: UserRepository, name: str, secret: str, source: str,
          now: datetime | None = None) -> UserLogin:
    """Check a user's PIN or password. UnauthenticatedError for an unknown name or a wrong
    secret (the same words for both), TooManyAttemptsError while the user has to wait,
    ForbiddenError for a locked or disabled user. Everything is audited."""
    now = now or datetime.now(UTC)
    found = repo.secret(name)
    if found is None:
        verify_secret(secret, _DUMMY)
        raise UnauthenticatedError("unknown user or wrong PIN or password")
    info = found.info
    if info.locked_at is not None:
        repo.refused(name, "locked", source)
        raise ForbiddenError(f"user {name!r} is locked after {LOCK_AFTER} wrong "
                             f"{_word(info.secret_kind)}s in a row: an engineer resets it "
                             f"(mvpose user reset {name})")
    wait = wait_s(info.failed_count)
    if wait and found.last_failed_at is not None:
        left = wait - (now - found.last_failed_at).total_seconds()
        if left > 0:
            repo.refused(name, f"{left:.0f} s left to wait", source)
            raise TooManyAttemptsError(
                f"{info.failed_count} wrong {_word(info.secret_kind)}s in a row for {name!r}: "
                f"try again in {left:.0f} s", retry_after_s=round(left))
    if not verify_secret(secret, found.secret_hash):
        count, locked = repo.failed(name, LOCK_AFTER, source, now)
        if locked:
            raise ForbiddenError(f"user {name!r} is now locked after {count} wrong "
                                 f"{_word(info.secret_kind)}s in a row: an engineer resets it "
                                 f"(mvpose user reset {name})")
        if wait_s(count):
            raise TooManyAttemptsError(
                f"wrong {_word(info.secret_kind)}, {count} in a row for {name!r}: try again "
                f"in {wait_s(count):.0f} s", retry_after_s=round(wait_s(count)))
        raise UnauthenticatedError("unknown user or wrong PIN or password")
    if info.disabled_at is not None:
        repo.refused(name, "disabled", source)
        raise ForbiddenError(f"user {name!r} is disabled; an engineer enables it again")
    repo.logged_in(name, source)
    return UserLogin(Principal(name=name, role=Role(info.role)), found.epoch)


def session_principal(repo: UserRepository, name: str, epoch: int) -> Principal | None:
    """The user behind a page session opened at ``epoch``, with the role the user has now;
    None once the user is disabled, reset or gone (the session is over)."""
    found = repo.secret(name)
    if found is None or found.epoch != epoch or found.info.disabled_at is not None:
        return None
    return Principal(name=name, role=Role(found.info.role))


def add_user(repo: UserRepository, name: str, role: Role, kind: SecretKind, secret: str,
             actor: str) -> UserInfo:
    check_secret(kind, secret)
    return repo.create(name, role.value, kind.value, hash_secret(secret), actor)


def reset_user(repo: UserRepository, name: str, kind: SecretKind, secret: str,
               actor: str) -> UserInfo:
    """A new PIN or password: unlocks the user and ends its open sessions."""
    check_secret(kind, secret)
    repo.info(name)  # NotFoundError before the hash's cost
    return repo.reset(name, kind.value, hash_secret(secret), actor)
