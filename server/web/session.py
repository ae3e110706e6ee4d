"""Operator-page sessions: a token typed once becomes an HTTP-only, SameSite=Strict cookie.

The cookie holds a random session id, never the token; the process keeps ``id -> token`` in
memory (an API restart logs everyone out). Every request with the cookie is checked like a
bearer token (server.auth), so a revoked token ends its sessions at once. Requests that change
something (POST, PUT, PATCH, DELETE) with the cookie must also come from the page itself: the
``Origin`` (or, without it, ``Referer``) must name this host, and SameSite=Strict keeps the
cookie off requests started by other sites in the first place.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from starlette.requests import HTTPConnection

from server.errors import ForbiddenError

COOKIE = "mvpose_session"
#: a session ends this long after login (a shift and a half)
MAX_AGE_S = 12 * 3600
_SAFE = frozenset({"GET", "HEAD", "OPTIONS"})


@dataclass
class Sessions:
    """Logged-in sessions of this process: session id -> (token secret, expiry)."""

    max_age_s: float = MAX_AGE_S
    clock: Callable[[], float] = time.monotonic
    _items: dict[str, tuple[str, float]] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def open(self, secret: str) -> str:
        sid = secrets.token_urlsafe(32)
        now = self.clock()
        with self._lock:
            self._items = {k: v for k, v in self._items.items() if v[1] > now}
            self._items[sid] = (secret, now + self.max_age_s)
        return sid

    def secret(self, sid: str) -> str | None:
        hit = self._items.get(sid)
        if hit is None or hit[1] <= self.clock():
            return None
        return hit[0]

    def close(self, sid: str) -> None:
        with self._lock:
            self._items.pop(sid, None)


def sessions_of(conn: HTTPConnection) -> Sessions | None:
    found = getattr(conn.app.state, "web_sessions", None)
    return found if isinstance(found, Sessions) else None


def same_origin(conn: HTTPConnection) -> bool:
    """Whether the request names this host as its origin (Origin, else Referer)."""
    source = conn.headers.get("origin") or conn.headers.get("referer")
    if not source or source == "null":
        return False
    return urlsplit(source).netloc == conn.headers.get("host", "")


def cookie_authorization(conn: HTTPConnection) -> str | None:
    """``Bearer <token>`` of the request's session cookie, None without a live session.

    A state-changing request that carries the cookie from another origin is refused
    (ForbiddenError): that is a cross-site request forgery, whatever the session."""
    sid = conn.cookies.get(COOKIE)
    sessions = sessions_of(conn)
    if not sid or sessions is None:
        return None
    secret = sessions.secret(sid)
    if secret is None:
        return None
    method = conn.scope.get("method", "GET")
    if method not in _SAFE and not same_origin(conn):
        raise ForbiddenError(
            f"{method} with the operator page's session cookie must come from this page "
            f"(Origin {conn.headers.get('origin')!r} is not host {conn.headers.get('host')!r})"
        )
    return f"Bearer {secret}"
