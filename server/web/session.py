"""Operator-page sessions: a login (a user's PIN or password, or an API token) becomes an
HTTP-only, SameSite=Strict cookie.

The cookie holds a random session id, never a secret; the process keeps ``id -> who`` in memory
(an API restart logs everyone out). ``who`` is a user's name and session epoch, or an API
token's secret. Every request with the cookie is checked again: a token like a bearer token (a
revoked token ends its sessions at once), a user against the store (disabled, reset or deleted:
the session is over; a new role applies to the next request). A session also ends
``idle_logout_s`` (the station file's ``page:``) after its user's last action: a login, a
request that changes something, a page opened by a click (``Sec-Fetch-User: ?1``), or the
page's own report of a click or key (POST /web/session/activity); background refreshes (the
Live page's events, the line view's and History's polling) do not count.

Requests that change something (POST, PUT, PATCH, DELETE) with the cookie must also come from
the page itself: the ``Origin`` (or, without it, ``Referer``) must name this host, and
SameSite=Strict keeps the cookie off requests started by other sites in the first place.
"""

from __future__ import annotations

import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from mvpose_core.station import IDLE_LOGOUT_S
from server.auth import Principal, authenticate, authenticate_recent
from server.errors import ForbiddenError, UnauthenticatedError
from server.state import Services
from server.users import session_principal

COOKIE = "mvpose_session"
#: a session ends this long after login at the latest (a shift and a half)
MAX_AGE_S = 12 * 3600
_SAFE = frozenset({"GET", "HEAD", "OPTIONS"})


@dataclass(frozen=True)
class Who:
    """Who a session is: a user (name and session epoch) or an API token's secret."""

    user: str | None = None
    epoch: int = 0
    token: str | None = None


@dataclass
class _Entry:
    who: Who
    expires: float
    last_action: float


@dataclass
class Sessions:
    """Logged-in sessions of this process: session id -> who, expiry and last user action."""

    max_age_s: float = MAX_AGE_S
    clock: Callable[[], float] = time.monotonic
    _items: dict[str, _Entry] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def open(self, who: Who) -> str:
        sid = secrets.token_urlsafe(32)
        now = self.clock()
        with self._lock:
            self._items = {k: v for k, v in self._items.items() if v.expires > now}
            self._items[sid] = _Entry(who, now + self.max_age_s, now)
        return sid

    def get(self, sid: str, idle_s: float) -> Who | None:
        """Who the session is; None when there is none, or it expired or sat idle past
        ``idle_s`` (then it is closed)."""
        hit = self._items.get(sid)
        if hit is None:
            return None
        now = self.clock()
        if hit.expires <= now or now - hit.last_action > idle_s:
            self.close(sid)
            return None
        return hit.who

    def touch(self, sid: str) -> None:
        """The session's user did something just now."""
        hit = self._items.get(sid)
        if hit is not None:
            hit.last_action = self.clock()

    def idle_left_s(self, sid: str, idle_s: float) -> float:
        """Seconds until the session ends for want of a user action (0 when it has)."""
        hit = self._items.get(sid)
        if hit is None:
            return 0.0
        now = self.clock()
        return max(0.0, min(hit.last_action + idle_s, hit.expires) - now)

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


def idle_logout_s(services: Services) -> float:
    """The station file's idle logout (``page: {idle_logout_s}``); its default without one."""
    return services.station.page.idle_logout_s if services.station else IDLE_LOGOUT_S


def user_action(conn: HTTPConnection) -> bool:
    """Whether the request is its user's doing: it changes something (the page sends those
    on a click), or it opens a page the user clicked to (the browser's Sec-Fetch headers)."""
    if conn.scope.get("method", "GET") not in _SAFE:
        return True
    return conn.headers.get("sec-fetch-mode") == "navigate" and \
        conn.headers.get("sec-fetch-user") == "?1"


def cookie_session(conn: HTTPConnection, services: Services) -> Who | None:
    """Who the request's session cookie is, None without a live session; a user action
    (:func:`user_action`) restarts the idle time.

    A state-changing request that carries the cookie from another origin is refused
    (ForbiddenError): that is a cross-site request forgery, whatever the session."""
    sid = conn.cookies.get(COOKIE)
    sessions = sessions_of(conn)
    if not sid or sessions is None:
        return None
    who = sessions.get(sid, idle_logout_s(services))
    if who is None:
        return None
    method = conn.scope.get("method", "GET")
    if method not in _SAFE and not same_origin(conn):
        raise ForbiddenError(
            f"{method} with the operator page's session cookie must come from this page "
            f"(Origin {conn.headers.get('origin')!r} is not host {conn.headers.get('host')!r})"
        )
    if user_action(conn):
        sessions.touch(sid)
    return who


async def cookie_principal(conn: HTTPConnection, services: Services) -> Principal | None:
    """The principal of the request's session cookie, with its role as it is now; None
    without a live session (a session whose user was disabled or reset is closed here)."""
    who = cookie_session(conn, services)
    if who is None:
        return None
    if who.token is not None:
        tokens, header = services.store.tokens, f"Bearer {who.token}"
        try:
            return authenticate_recent(tokens, header) or await run_in_threadpool(
                authenticate, tokens, header)
        except UnauthenticatedError:
            return None
    if who.user is None:
        return None
    principal = await run_in_threadpool(session_principal, services.store.users, who.user,
                                        who.epoch)
    sessions, sid = sessions_of(conn), conn.cookies.get(COOKIE)
    if principal is None and sessions is not None and sid:
        sessions.close(sid)
    return principal
