"""The line view (/line): what a panel PC beside the line shows all shift, read from 2 m.

A verdict tile (OK green, NOK red, station down grey, each with the word), the station's and
the link's state in words, the shift's counts, yield and cycle times from the store (they
survive restarts and reset at each shift start of the station file), the last NOKs with a
thumbnail, the reason in words and what to check, and a warning after the recipe's
``nok_streak_warning`` NOKs in a row. The page polls one fragment (htmx, every
:data:`POLL_S`); everything it reads comes from the store and the station's status, so it never
delays a trigger. With the station file's ``page: {kiosk: true}`` it is readable without a login,
read-only (a kiosk).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request
from fastapi.responses import HTMLResponse, Response

from mvpose_core.shifts import ShiftWindow
from server.auth import Principal, Role
from server.errors import NotFoundError, UnauthenticatedError
from server.store.alarms import Alarm
from server.store.schemas import MAX_ID, MeasurementFilter, MeasurementSummary
from server.store.shifts import ShiftCounts
from server.web import alarms as alarm_words
from server.web import html, i18n
from server.web.context import in_thread, need, page_user, reader_of, station_status, zone_of
from server.web.i18n import N_, _, ngettext
from server.web.pages import Html, frame_response, to_login
from server.web.reader import Reader

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])
#: seconds between the page's refreshes
POLL_S = 2
#: NOKs in the strip
LAST_NOKS = 6
#: thumbnail width, px
THUMB_W = 320


#: the station's states (OPC 40100's, as the PLC reads them) in words
STATES = {"READY": N_("ready"), "SINGLE_EXECUTION": N_("measuring"),
          "PREOPERATIONAL": N_("waiting for the PLC"), "HALTED": N_("halted (trigger disabled)"),
          "INITIALIZED": N_("no recipe selected"),
          "ERROR": N_("error, needs a reset"), "STOPPED": N_("link stopped")}


@dataclass(frozen=True)
class LineFigures:
    """Everything the line view shows, read once per refresh."""

    newest: MeasurementSummary | None
    status: dict[str, Any] | None
    window: ShiftWindow
    counts: ShiftCounts
    streak: int
    streak_limit: int
    recipe: str | None
    noks: list[tuple[MeasurementSummary, str | None]]  # and a thumbnail's URL
    alarms: list[Alarm] = field(default_factory=list)  # standing, newest first


def read_figures(reader: Reader, app: Any) -> LineFigures:
    """Blocking: the store's figures and the station's status."""
    store = reader.store
    page, _next = store.measurements.summary_page(MeasurementFilter(), None, 1)
    status, _why = station_status(app)
    window, counts = reader.shift()
    active = reader.active_recipe()
    limit = active[2].nok_streak_warning if active and active[2] is not None else 3
    noks, _next = store.measurements.summary_page(MeasurementFilter(result="NOK"), None, LAST_NOKS)
    strip = []
    for m in noks:
        on_disk = [i for i in store.images.for_measurement(m.id) if i.evicted_at is None]
        thumb = (f"/web/line/thumb/{m.id}/{on_disk[0].view}/{on_disk[0].camera_id}"
                 if on_disk else None)
        strip.append((m, thumb))
    return LineFigures(page[0] if page else None, status, window, counts,
                       store.shifts.nok_streak(), limit, active[0] if active else None, strip,
                       store.alarms.standing())


def kiosk(request: Request) -> bool:
    """Whether the line view is public (the station file's ``page: {kiosk: true}``)."""
    station = request.state.services.station
    return bool(station is not None and station.page.kiosk)


async def line_user(request: Request) -> Principal | None:
    """The logged-in user, or None on a public (kiosk) line view; 401 otherwise."""
    user = await page_user(request)
    if user is None and not kiosk(request):
        raise UnauthenticatedError(_("log in on the operator page first (session expired?)"))
    return user


@router.get("/line")
async def line_page(request: Request) -> Html:
    """The line view: a whole screen for a panel PC."""
    user = await page_user(request)
    if user is None and not kiosk(request):
        return to_login(request)
    reader = reader_of(request)
    figures = await in_thread(read_figures, reader, request.app)
    body = render(figures, zone_of(reader))
    return HTMLResponse(html.layout(_("Line"), user, body, "/line", body_class="line"))


@router.get("/web/line/fragment")
async def line_fragment(request: Request) -> HTMLResponse:
    await line_user(request)
    reader = reader_of(request)
    figures = await in_thread(read_figures, reader, request.app)
    return HTMLResponse(render(figures, zone_of(reader)), headers={"Cache-Control": "no-store"})


@router.get("/web/line/thumb/{measurement_id}/{view}/{camera_id}")
async def line_thumb(
    request: Request,
    measurement_id: Annotated[int, Path(ge=1, le=MAX_ID)],
    view: Annotated[int, Path(ge=1, le=255)],
    camera_id: Annotated[str, Path(max_length=64)],
) -> Response:
    """A NOK's frame as a thumbnail (the only frames a public line view shows)."""
    user = await line_user(request)
    if user is None:
        stored = await in_thread(reader_of(request).store.measurements.get, measurement_id)
        if stored.record.result == "OK":
            raise NotFoundError(f"measurement {measurement_id} is not a NOK of the line view")
    else:
        await need(request, Role.READ)
    return await frame_response(request, measurement_id, view, camera_id, THUMB_W)


# ---------------------------------------------------------------------------- HTML
def render(f: LineFigures, zone: str) -> str:
    e = html.esc
    return f"""<div id="line-view" hx-get="/web/line/fragment" hx-trigger="every {POLL_S}s"
 hx-swap="outerHTML" data-newest="{f.newest.id if f.newest else ''}">
<div class="line-grid"><section aria-label=\"""" + e(_("last result")) + f"""">{tile(f)}{states(f)}\
{streak(f)}{alarm_banner(f)}</section>
<section class="panel shift" aria-label=\"""" + e(_("this shift")) + """">
<h2>""" + e(_("This shift")) + f"""</h2>
{shift_table(f, zone)}</section></div>
<section class="panel line-noks" aria-label=\"""" + e(_("last NOKs")) + """">
<h2>""" + e(_("Last NOKs")) + f"""</h2>
{nok_strip(f)}</section>
</div>"""


def tile(f: LineFigures) -> str:
    m = f.newest
    e = html.esc
    if f.status is None:
        kind, word = "down", e(_("STATION DOWN"))
        words = e(_("the station process does not answer")) + (
            " · " + e(_("last result #{id}").format(id=m.id)) + " " +
            html.verdict_word(m.result) if m else "")
    elif m is None:
        kind, word, words = "none", "—", e(_("no result yet"))
    else:
        kind, word = (("ok", html.ok_word()) if m.result == "OK" else ("nok", html.nok_word()))
        words = (f'<a href="/history/{m.id}">#{m.id}</a> · {e(m.reason)}: '
                 f"{e(i18n.reason_words(m.reason_code))} · {e(m.part_id or '')} · "
                 f"{html.when(m.triggered_at)}")
    return (f'<div id="verdict" class="tile {kind}" data-verdict="{kind.upper()}">'
            f'<p class="verdict-word">{word}</p>'
            f'<p class="tile-words">{words}</p></div>')


def states(f: LineFigures) -> str:
    if f.status is None:
        station, link, good_s, good_l = _("station down"), _("link: unknown"), False, False
    else:
        state = str(f.status.get("state", "?"))
        station = _("station: {state}").format(state=_(STATES[state]) if state in STATES
                                               else state)
        good_s = state in ("READY", "SINGLE_EXECUTION")
        links = f.status.get("links") or ({"plc": f.status["plc"]} if f.status.get("plc")
                                          else {})
        words = [f"{name}: {html.link_words(v)}" for name, v in links.items()]
        link = "; ".join(words) if words else _("no link configured")
        good_l = bool(words) and all(_link_good(v) for v in links.values())
    return (f'<div class="line-state"><p id="station-state" class="{"good" if good_s else "bad"}">'
            f'{html.esc(station)}</p><p id="link-state" class="{"good" if good_l else "bad"}">'
            f"{html.esc(link)}</p></div>")


def _link_good(v: object) -> bool:
    """A link that runs and whose PLC is not offline."""
    if not isinstance(v, Mapping):
        return "offline" not in str(v) and "not running" not in str(v)
    return bool(v.get("state") or v.get("running")) and v.get("plc_online") is not False


def streak(f: LineFigures) -> str:
    if f.streak < f.streak_limit:
        return ""
    e = html.esc
    hint = (" " + e(_("Check: {what}.").format(what=i18n.check_words(f.noks[0][0].reason_code)))
            if f.noks else "")
    words = ngettext("{n} NOK in a row (warning from {limit}, recipe {recipe}).",
                     "{n} NOKs in a row (warning from {limit}, recipe {recipe}).", f.streak)
    return (f'<p class="streak" role="alert" data-streak="{f.streak}">⚠ '
            f"{e(words.format(n=f.streak, limit=f.streak_limit, recipe=f.recipe or '—'))}"
            f"{hint}</p>")


def alarm_banner(f: LineFigures) -> str:
    """The standing alarms: how many, and the newest active one in words."""
    if not f.alarms:
        return ""
    active = [a for a in f.alarms if a.active]
    unacked = sum(1 for a in f.alarms if not a.acknowledged)
    top = max(f.alarms, key=lambda a: ({"high": 3, "medium": 2}.get(a.priority, 1), a.id))
    newest = active[0] if active else f.alarms[0]
    return (f'<p id="alarm-banner" class="alarm-banner {html.esc(top.priority)}" role="alert" '
            f'data-active="{len(active)}" data-unacked="{unacked}">⚠ <a href="/alarms">'
            + html.esc(alarm_words.count_words(len(active), unacked)) + "</a>: "
            + html.esc(alarm_words.words(newest)) + "</p>")


def shift_table(f: LineFigures, zone: str) -> str:
    c = f.counts
    e = html.esc
    span = html.shift_span(f.window, zone)

    def ms(v: float | None) -> str:
        return f"{html.num(v, 1)} ms" if v is not None else "—"

    return (f'<p class="muted">{span}</p><dl>'
            f'<dt>{html.ok_word()}</dt><dd data-count="ok">{c.ok}</dd>'
            f'<dt>{html.nok_word()}</dt><dd data-count="nok">{c.nok}</dd>'
            f'<dt>' + e(_("yield")) + f'</dt><dd data-count="yield">{i18n.pct(c.yield_pct)}</dd>'
            f'<dt>' + e(_("cycle min")) + f'</dt><dd data-count="min">{ms(c.min_ms)}</dd>'
            f'<dt>' + e(_("cycle mean")) + f'</dt><dd data-count="mean">{ms(c.mean_ms)}</dd>'
            f'<dt>' + e(_("cycle max")) + f'</dt><dd data-count="max">{ms(c.max_ms)}</dd></dl>')


def nok_strip(f: LineFigures) -> str:
    e = html.esc
    if not f.noks:
        return '<p class="muted">' + e(_("No NOK results.")) + '</p>'
    items = []
    for m, thumb in f.noks:
        alt = _("frame of NOK #{id}").format(id=m.id)
        img = (f'<img src="{e(thumb)}" alt="{e(alt)}" loading="lazy">'
               if thumb else '<span class="noimg">' + e(_("no frame kept")) + '</span>')
        check = _("Check: {what}").format(what=i18n.check_words(m.reason_code))
        items.append(
            f'<li data-id="{m.id}" data-reason="{m.reason_code}">{img}'
            f'<span class="when">#{m.id} · {html.when(m.triggered_at)}</span><br>'
            f'<span class="reason">{e(m.reason)}</span>: {e(i18n.reason_words(m.reason_code))}'
            f'<br><span class="check">{e(check)}</span></li>')
    return f'<ul class="noks">{"".join(items)}</ul>'
