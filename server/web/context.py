"""Per-request context of the operator page: who is logged in, the reader, the station handle."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import anyio.to_thread
from fastapi import Request

from mvpose_core.station import RecipeConfig
from server.auth import Principal, Role
from server.errors import ForbiddenError, UnauthenticatedError
from server.state import Services
from server.web import html, i18n
from server.web.i18n import _
from server.web.live import LiveFeed, LiveFeeds
from server.web.reader import Reader, RecordView, age_words
from server.web.session import cookie_principal

if TYPE_CHECKING:  # server.app imports this package
    from server.app import StationHandle

#: where the drift engineer's detector answers (server/api/drift.py); the page shows it if mounted
DRIFT_ENDPOINT = "/api/v1/drift"
#: the drift engineer's reference-part check (POST, operator)
VERIFY_ENDPOINT = "/api/v1/calibration/verify"


async def page_user(request: Request) -> Principal | None:
    """The logged-in principal of the page's session cookie, or None (log in first)."""
    return await cookie_principal(request, request.state.services)


async def need(request: Request, role: Role) -> Principal:
    """The session's principal if it may do what needs ``role`` (401/403 otherwise)."""
    user = await page_user(request)
    if user is None:
        raise UnauthenticatedError(_("log in on the operator page first (session expired?)"))
    if not user.role.allows(role):
        raise ForbiddenError(_("{name} has role {role}; this needs {needed}").format(
            name=repr(user.name), role=repr(user.role.value), needed=repr(role.value)))
    return user


def services_of(request: Request) -> Services:
    services: Services = request.state.services
    return services


def reader_of(request: Request) -> Reader:
    """One Reader (and its caches) per open Services of this process."""
    services = services_of(request)
    reader: Reader | None = getattr(request.app.state, "web_reader", None)
    if reader is None or reader.services is not services:
        reader = Reader(services)
        request.app.state.web_reader = reader
        request.app.state.web_live = LiveFeeds(lambda code: live_in(request.app, reader, code))
    return reader


def live_in(app: Any, reader: Reader, code: str) -> LiveFeed:
    """The Live page's feed in language ``code`` (its fragments rendered in it)."""
    zone = zone_of(reader)

    def result(reader: Reader, newest: int | None,
               frames_id: int | None) -> tuple[str, str, int | None, bool]:
        with i18n.use(code, zone):
            return render_live_result(reader, newest, frames_id)

    def status() -> str:
        with i18n.use(code, zone):
            return render_status(app, reader)

    return LiveFeed(reader, result, status)


def live_feed(request: Request) -> LiveFeed:
    reader_of(request)
    feeds: LiveFeeds = request.app.state.web_live
    return feeds.of(i18n.current().code)


def runtime_of(app: Any) -> StationHandle | None:
    """The station handle (server.station.client.StationClient on ``app.state.station``)."""
    runtime: StationHandle | None = getattr(app.state, "station", None)
    return runtime


def station_status(app: Any) -> tuple[dict[str, Any] | None, str | None]:
    """``runtime.status()``, or (None, why) when the station is down. Blocking."""
    runtime = runtime_of(app)
    if runtime is None:
        return None, None
    try:
        return runtime.status().model_dump(mode="json"), None
    except Exception as err:  # a station handle that cannot answer is a station that is down
        return None, _("the station does not answer: {error}").format(
            error=f"{type(err).__name__}: {err}")


def has_endpoint(app: Any, path: str, method: str) -> bool:
    """Whether the app answers ``method path`` (from its OpenAPI, which FastAPI caches)."""
    return method.lower() in app.openapi().get("paths", {}).get(path, {})


def station_up(app: Any) -> bool:
    """Whether the station answers (its actions are offered only then). Blocking."""
    return station_status(app)[0] is not None


def calibration_words(reader: Reader) -> str:
    """The active calibration(s) from the store, with age; the station file's otherwise."""
    from datetime import UTC, datetime

    store, now = reader.store, datetime.now(UTC)
    out = []
    for n in store.versions.names("calibration"):
        if n.active_version is None:
            continue
        info, _content = store.versions.content("calibration", n.name, n.active_version)
        out.append(f"{html.esc(n.name)} v{n.active_version} (" + html.esc(_("{age} old").format(
            age=age_words(info.created_at, now))) + ")")
    if out:
        return ", ".join(out)
    station = reader.services.settings.station
    return html.esc(_("station file {name}").format(
        name=station.name if station else _("(none)")))


def render_status(app: Any, reader: Reader) -> str:
    status, error = station_status(app)
    window, counts = reader.shift()
    return html.status_panel(status, error, calibration_words(reader),
                             html.shift_words(window, counts, zone_of(reader)))


def zone_of(reader: Reader) -> str:
    station = reader.services.station
    return station.time_zone if station is not None else "UTC"


def deadline_ms(reader: Reader) -> float | None:
    station = reader.services.station
    return station.deadline_ms if station is not None else None


def render_live_result(reader: Reader, newest: int | None,
                       frames_id: int | None) -> tuple[str, str, int | None, bool]:
    """The Live page's result and frames panels, both of the newest record: its frames where
    the archive has them (NOK always, OK 1 in N), its overlays always. A record that kept no
    frames links to the newest one that did (``frames_id``: the last one known), never shows
    that older record's images next to its own result. Returns the panels, the newest record
    with frames, and whether the newest record's planned frames are all on disk yet."""
    if newest is None:
        empty = ('<section id="result" class="panel"><h2>' + html.esc(_("Last result")) + '</h2>'
                 '<p>' + html.esc(_("none yet")) + '</p></section>')
        return empty, html.frames_panel(None, None), None, True
    view = reader.get(newest)
    planned = {(i.view, i.camera_id) for i in view.stored.record.images}
    complete = planned <= set(view.frames)
    framed: RecordView | None = view if view.has_frames else None
    if framed is None and frames_id is not None:
        hint = reader.get(frames_id)
        framed = hint if hint.has_frames else None
    if framed is None:
        framed = reader.latest_with_frames()
    return (html.result_panel(newest, view.stored.record, deadline_ms(reader)),
            html.frames_panel(view, framed), framed.stored.id if framed else None, complete)


async def in_thread(fn: Any, *args: Any) -> Any:
    return await anyio.to_thread.run_sync(fn, *args)


@dataclass(frozen=True)
class TeachPreview:
    """What teaching a measurement as the new reference implies for the robot."""

    recipe: RecipeConfig
    values: list[float]
    grasp_displacement_mm: float
    rotation_deg: float
