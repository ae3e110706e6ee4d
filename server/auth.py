"""API tokens: roles read < operator < engineer, secrets stored only as sha256, bearer check.

Tokens are 256-bit random secrets, so a single sha256 is enough to store them (a slow password
hash only helps against guessing low-entropy secrets). The first token comes from the
environment: ``MVPOSE_BOOTSTRAP_TOKEN`` is ensured at start-up as the engineer token named
``bootstrap``; that engineer then creates the others with ``POST /api/v1/tokens``.
"""

from __future__ import annotations

import hashlib
import secrets
from dataclasses import dataclass
from enum import StrEnum

from server.errors import ForbiddenError, InvalidInputError, UnauthenticatedError
from server.store.tokens import TokenInfo, TokenRepository

TOKEN_PREFIX = "mvp_"
BOOTSTRAP_NAME = "bootstrap"


class Role(StrEnum):
    """What a token may do: read (MES), operator (trigger, teach), engineer (changes, tokens)."""

    READ = "read"
    OPERATOR = "operator"
    ENGINEER = "engineer"

    @property
    def rank(self) -> int:
        return _RANK[self]

    def allows(self, needed: Role) -> bool:
        return self.rank >= needed.rank


_RANK = {Role.READ: 0, Role.OPERATOR: 1, Role.ENGINEER: 2}


@dataclass(frozen=True)
class Principal:
    """Who made a request."""

    name: str
    role: Role


def new_secret() -> str:
    return TOKEN_PREFIX + secrets.token_urlsafe(32)


def hash_secret(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def create_token(repo: TokenRepository, name: str, role: Role) -> tuple[str, TokenInfo]:
    """A new token; the secret is returned once and never stored."""
    secret = new_secret()
    return secret, repo.create(name, role.value, hash_secret(secret))


def ensure_bootstrap(repo: TokenRepository, secret: str) -> TokenInfo:
    if len(secret) < 16:
        raise InvalidInputError(
            f"MVPOSE_BOOTSTRAP_TOKEN must have at least 16 characters, got {len(secret)}"
        )
    return repo.upsert_secret(BOOTSTRAP_NAME, Role.ENGINEER.value, hash_secret(secret))


def bearer_hash(authorization: str | None) -> str:
    """The sha256 of the token in an ``Authorization: Bearer <token>`` header, or
    UnauthenticatedError naming what is wrong with the header."""
    if not authorization:
        raise UnauthenticatedError(
            "missing Authorization header; send 'Authorization: Bearer <token>'"
        )
    scheme, _, secret = authorization.partition(" ")
    if scheme.lower() != "bearer" or not secret.strip():
        raise UnauthenticatedError(f"Authorization scheme {scheme[:20]!r} is not 'Bearer <token>'")
    return hash_secret(secret.strip())


def authenticate(repo: TokenRepository, authorization: str | None) -> Principal:
    """The principal behind an ``Authorization: Bearer <token>`` header, or UnauthenticatedError."""
    # The lookup is by the hash (a unique index): timing can reveal the hash's prefix at most,
    # never the secret, so no constant-time compare of secrets is needed.
    info = repo.by_hash(bearer_hash(authorization))
    if info is None:
        raise UnauthenticatedError("unknown or revoked token")
    return Principal(name=info.name, role=Role(info.role))


def authenticate_recent(repo: TokenRepository, authorization: str | None) -> Principal | None:
    """:func:`authenticate` without a query, for a token verified within the repository's TTL
    (:meth:`TokenRepository.recent`); None when it has to be looked up. A malformed header
    raises UnauthenticatedError here already."""
    info = repo.recent(bearer_hash(authorization))
    return Principal(name=info.name, role=Role(info.role)) if info is not None else None


def authorize(principal: Principal, needed: Role) -> Principal:
    if not principal.role.allows(needed):
        raise ForbiddenError(
            f"token {principal.name!r} has role {principal.role.value!r}; "
            f"this needs {needed.value!r}"
        )
    return principal
