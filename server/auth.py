"""API tokens: roles read < operator < engineer, secrets stored only as sha256, bearer check.

Tokens are 256-bit random secrets, so a single sha256 is enough to store them (a slow password
hash only helps against guessing low-entropy secrets). The first token comes from the
environment: ``MVPOSE_BOOTSTRAP_TOKEN`` is ensured at start-up as the engineer token named
``bootstrap``; that engineer then creates the others with ``POST /api/v1/tokens``.
"""

from __future__ import annotations

import hashlib
import logging
import secrets
from dataclasses import dataclass
from enum import StrEnum

from server.errors import ForbiddenError, InvalidInputError, UnauthenticatedError
from server.store.tokens import TokenInfo, TokenRepository

log = logging.getLogger(__name__)

TOKEN_PREFIX = "mvp_"
BOOTSTRAP_NAME = "bootstrap"
BOOTSTRAP_MIN_LENGTH = 16
#: the command that makes the first engineer token when no bootstrap token is configured
CREATE_COMMAND = "mvpose token create NAME --role engineer"

# HTTP authentication schemes (IANA registry and common ones) that may be named back in a 401:
# anything else in front of the first space may be the secret itself, sent without a scheme.
_KNOWN_SCHEMES = frozenset({
    "basic", "bearer", "digest", "dpop", "gnap", "hoba", "mutual", "negotiate", "ntlm",
    "oauth", "privatetoken", "scram-sha-1", "scram-sha-256", "token", "vapid",
    "aws4-hmac-sha256", "apikey",
})


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


def check_bootstrap_secret(secret: str) -> None:
    """InvalidInputError unless ``secret`` is long enough to be the bootstrap token."""
    if len(secret) < BOOTSTRAP_MIN_LENGTH:
        raise InvalidInputError(
            f"MVPOSE_BOOTSTRAP_TOKEN must have at least {BOOTSTRAP_MIN_LENGTH} characters, "
            f"got {len(secret)}"
        )


def ensure_bootstrap(repo: TokenRepository, secret: str) -> TokenInfo:
    check_bootstrap_secret(secret)
    return repo.upsert_secret(BOOTSTRAP_NAME, Role.ENGINEER.value, hash_secret(secret))


def ensure_access(repo: TokenRepository, bootstrap_secret: str | None) -> TokenInfo | None:
    """At start-up: ensure the bootstrap token if one is configured; otherwise warn when no live
    engineer token exists (nobody could create tokens or change anything), naming the command
    that creates one. Returns the bootstrap token's info, or None."""
    if bootstrap_secret is not None:
        return ensure_bootstrap(repo, bootstrap_secret)
    if repo.live_count(Role.ENGINEER.value) == 0:
        log.warning(
            "no engineer token exists and MVPOSE_BOOTSTRAP_TOKEN is not set: nobody can create "
            "tokens or change recipes. Create one with `%s` (with the same MVPOSE_DATA_DIR / "
            "MVPOSE_DATABASE_URL / --station as the server; it prints the secret once) or set "
            "MVPOSE_BOOTSTRAP_TOKEN (at least %d characters) and restart",
            CREATE_COMMAND, BOOTSTRAP_MIN_LENGTH,
        )
    return None


def bearer_hash(authorization: str | None) -> str:
    """The sha256 of the token in an ``Authorization: Bearer <token>`` header, or
    UnauthenticatedError naming what is wrong with the header."""
    if not authorization:
        raise UnauthenticatedError(
            "missing Authorization header; send 'Authorization: Bearer <token>'"
        )
    scheme, _, secret = authorization.strip().partition(" ")
    if scheme.lower() != "bearer":
        # Never echo what was sent: without a scheme, the first word is the secret itself.
        named = f"scheme {scheme!r}" if scheme.lower() in _KNOWN_SCHEMES else (
            "a value without the Bearer scheme (not shown: it may be the secret)")
        raise UnauthenticatedError(
            f"Authorization header has {named}; send 'Authorization: Bearer <token>'")
    if not secret.strip():
        raise UnauthenticatedError(
            "Authorization header 'Bearer' has no token; send 'Authorization: Bearer <token>'")
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
