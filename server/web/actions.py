"""Operator page: log in and out (a user's PIN or password, or an API token), the session's
idle time, and the actions (trigger, teach, activate) through the station.

Actions go to the station handle (``app.state.runtime``: the station process's control channel)
with the session's name as the author; activating a recipe version with the station down is
recorded in the store, which the station reads at its next start (as the REST API does).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated, Any
from urllib.parse import urlsplit

from fastapi import APIRouter, Body, Depends, Query, Request
from fastapi.responses import HTMLResponse, JSONResponse, RedirectResponse, Response
from pydantic import BaseModel, Field, model_validator
from starlette.concurrency import run_in_threadpool

from mvpose_core.reasons import reason_name
from server import users
from server.auth import Role, authenticate
from server.errors import ForbiddenError, NotReadyError
from server.users import NAME_PATTERN
from server.web import html, i18n
from server.web.context import in_thread, need, page_user, runtime_of, services_of
from server.web.i18n import _
from server.web.session import (
    COOKIE,
    MAX_AGE_S,
    Sessions,
    Who,
    idle_logout_s,
    same_origin,
    sessions_of,
)

if TYPE_CHECKING:  # server.app imports this package
    from server.app import StationHandle

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])


class Login(BaseModel):
    """A user's name and PIN or password, or (without a user) an API token."""

    user: str | None = Field(None, min_length=1, max_length=64, pattern=NAME_PATTERN)
    secret: str | None = Field(None, min_length=1, max_length=200)
    token: str | None = Field(None, min_length=1, max_length=200)

    @model_validator(mode="after")
    def _one_way(self) -> Login:
        if (self.token is None) == (self.user is None and self.secret is None):
            raise ValueError("send either user and secret (a PIN or password), or token")
        if self.token is None and (self.user is None or self.secret is None):
            raise ValueError("a user's login needs both user and secret (a PIN or password)")
        return self


class TriggerBody(BaseModel):
    part_id: str | None = Field(None, max_length=40, pattern=r"^[\x20-\x7e]*$")


class TeachBody(BaseModel):
    measurement_id: int = Field(ge=1, le=2**63 - 1, strict=True)


class ActivateBody(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9_.\-]+$", max_length=64)
    version: int = Field(ge=1, le=2**31 - 1, strict=True)


def _safe_next(target: str) -> str:
    # Only a path on this site: never an absolute URL (an open redirect after login).
    parts = urlsplit(target)
    return target if target.startswith("/") and not parts.netloc and not parts.scheme \
        and not target.startswith("//") else "/"


@router.get("/login")
async def login_page(request: Request,
                     next: Annotated[str, Query(max_length=200)] = "/",  # noqa: A002
                     idle: Annotated[int, Query(ge=0, le=1)] = 0) -> Response:
    if await page_user(request) is not None:
        return RedirectResponse(_safe_next(next), status_code=303)
    e = html.esc
    target = e(_safe_next(next))
    why = ('<p class="msg done" role="status" id="idle-note">'
           + e(_("You were logged out: nothing was done on the page for a while.")) + "</p>"
           if idle else "")
    idle_words = e(_("The page logs out after {duration} without a click or a key; the browser "
                     "only holds a session cookie.").format(
        duration=_duration(idle_logout_s(services_of(request)))))
    login_words, token_words = e(_("Log in")), e(_("token"))
    body = f"""<section class="panel login"><h2>{login_words}</h2>{why}
<form id="login-form" data-next="{target}">
<label>""" + e(_("user")) + """ <input name="user" autocomplete="username" required maxlength="64"
 autocapitalize="none" spellcheck="false"></label>
<label>""" + e(_("PIN or password")) + """ <input name="secret" type="password"
 autocomplete="current-password" required maxlength="200"></label>
<button type="submit">""" + login_words + """</button></form>
<p class="msg" role="alert"></p>
<details id="token-login"><summary>""" + e(_("Log in with an API token (engineers)")) + f"""\
</summary>
<form id="token-form" data-next="{target}">
<label>{token_words} <input name="token" type="password" autocomplete="off" required
 maxlength="200"></label><button type="submit">""" + e(_("Log in with the token")) + f"""\
</button></form>
<p class="msg" role="alert"></p></details>
<p>{idle_words}</p></section>"""
    return HTMLResponse(html.layout(_("Log in"), None, body, choose_language=True))


def _duration(seconds: float) -> str:
    if seconds >= 120:
        return _("{minutes} min").format(minutes=i18n.num(seconds / 60, 0 if seconds % 60 == 0
                                                          else 1))
    return _("{seconds} s").format(seconds=i18n.num(seconds, 0))


def _source(request: Request) -> str:
    return request.client.host if request.client else "?"


@router.post("/web/login")
async def login(request: Request, body: Annotated[Login, Body()]) -> Response:
    """Check a user's PIN or password (or an API token, like a bearer token); on success set
    the session cookie."""
    if not same_origin(request):
        raise ForbiddenError(_("log in from the operator page itself (Origin is not this host)"))
    sessions = sessions_of(request)
    if sessions is None:
        raise NotReadyError("sessions are not set up in this app")
    services = services_of(request)
    if body.token is not None:
        token = body.token.strip()
        principal = await run_in_threadpool(authenticate, services.store.tokens,
                                            f"Bearer {token}")
        who = Who(token=token)
    else:
        name = body.user or ""  # both are there: the model checked it
        done = await run_in_threadpool(users.login, services.store.users, name,
                                       body.secret or "", f"page {_source(request)}")
        principal, who = done.principal, Who(user=name, epoch=done.epoch)
    sid = sessions.open(who)
    resp = JSONResponse({"name": principal.name, "role": principal.role.value,
                         "idle_logout_s": idle_logout_s(services)})
    resp.set_cookie(COOKIE, sid, max_age=MAX_AGE_S, httponly=True, samesite="strict",
                    secure=request.url.scheme == "https", path="/")
    return resp


@router.post("/web/logout")
async def logout(request: Request) -> Response:
    if not same_origin(request):
        raise ForbiddenError(_("log out from the operator page itself (Origin is not this "
                               "host)"))
    sessions, sid = sessions_of(request), request.cookies.get(COOKIE)
    if sessions is not None and sid:
        sessions.close(sid)
    resp = JSONResponse({"logged_out": True})
    resp.delete_cookie(COOKIE, path="/", httponly=True, samesite="strict")
    return resp


async def _session_answer(request: Request) -> dict[str, Any]:
    user = await need(request, Role.READ)
    sessions, sid = sessions_of(request), request.cookies.get(COOKIE, "")
    idle = idle_logout_s(services_of(request))
    return {"name": user.name, "role": user.role.value, "idle_logout_s": idle,
            "idle_left_s": sessions.idle_left_s(sid, idle) if sessions else 0.0}


@router.get("/web/session")
async def session(request: Request) -> dict[str, Any]:
    """Who is logged in and how long the session has before the idle logout (a look, not a
    user action: it does not restart the idle time). 401 once the session is over."""
    return await _session_answer(request)


@router.post("/web/session/activity")
async def activity(request: Request) -> dict[str, Any]:
    """The page reports a click or a key: the idle time starts again."""
    return await _session_answer(request)


def _station(request: Request) -> StationHandle:
    runtime = runtime_of(request.app)
    if runtime is None:
        raise NotReadyError(_("station down: no station process is connected"))
    return runtime


@router.post("/web/actions/trigger")
async def trigger(request: Request,
                  body: Annotated[TriggerBody | None, Body()] = None) -> dict[str, Any]:
    await need(request, Role.OPERATOR)
    runtime = _station(request)
    out = await in_thread(lambda: runtime.trigger((body.part_id if body else None) or None, 0))
    # The control channel answers the result code and the station's message; the name is ours.
    reason, message = reason_name(out.result_code), out.message
    return {"message": f"{reason}: {message}" if message and message != reason else reason,
            "reason": reason, "result_code": out.result_code,
            "measurement_id": out.measurement_id}


@router.post("/web/actions/arm-teach")
async def arm_teach(request: Request) -> dict[str, Any]:
    user = await need(request, Role.OPERATOR)
    runtime = _station(request)
    await in_thread(runtime.arm_teach, user.name)
    return {"message": _("teach armed: the next OK result becomes the reference")}


@router.post("/web/actions/teach")
async def teach(request: Request, body: Annotated[TeachBody, Body()]) -> dict[str, Any]:
    user = await need(request, Role.OPERATOR)
    runtime = _station(request)
    rec = await in_thread(runtime.teach_from_measurement, body.measurement_id, user.name)
    version = rec.version
    return {"message": _("taught from measurement {id}: new version {version}").format(
        id=body.measurement_id, version=version), "version": version}


@router.post("/web/actions/activate")
async def activate(request: Request, body: Annotated[ActivateBody, Body()]) -> dict[str, Any]:
    user = await need(request, Role.ENGINEER)
    runtime = runtime_of(request.app)
    if runtime is not None:
        try:
            rec = await in_thread(runtime.activate_recipe, body.name, body.version, user.name)
        except NotReadyError:
            pass  # the station is down: the store takes it, as the REST API's activate does
        else:
            return {"message": _("{name} v{version} active").format(
                name=body.name, version=rec.version), "via": "station"}
    services = services_of(request)
    info = await in_thread(services.store.versions.activate, "recipe", body.name, body.version,
                           user.name)
    return {"message": _("{name} v{version} active (station down: it takes this version when "
                         "it starts)").format(name=info.name, version=info.version),
            "via": "store"}


def install_sessions(app: Any) -> Sessions:
    sessions = Sessions()
    app.state.web_sessions = sessions
    return sessions
