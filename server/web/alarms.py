"""Operator page: Alarms (/alarms): the standing alarms with acknowledge, the history with
filters, and the alarm count of the page header (docs/alarms.md).

The page reads the store (server/store/alarms.py) as REST does; acknowledge posts to
``/api/v1/alarms/{id}/acknowledge`` with the session (operator role or above), so the name
recorded is the session's principal's.
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, get_args
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse

from server.auth import Principal, Role
from server.store.alarms import Alarm, AlarmCounts, AlarmFilter, Priority
from server.web import html, i18n
from server.web.context import in_thread, page_user
from server.web.i18n import N_, _, ngettext
from server.web.pages import Html, to_login

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])
PAGE = 50  # history rows per page
_STATES = {"all": None, "active": True, "cleared": False}
_ACKED = {"any": None, "yes": True, "no": False}
#: the filters' and the table's words for the values the form and the store use
WORDS = {"all": N_("all"), "active": N_("active"), "cleared": N_("cleared"), "any": N_("any"),
         "yes": N_("yes"), "no": N_("no"), "high": N_("high"), "medium": N_("medium"),
         "low": N_("low")}
#: each alarm code's message (the store's text_key is alarm.<code>), with the alarm's text_args;
#: the store's English text is what a code missing here shows
TEXTS = {
    "LINK_DOWN": N_("link {link} is down"),
    "LINK_NO_PLC": N_("link {link}: no PLC heartbeat"),
    "LINK_ERROR": N_("link {link} is in ERROR and needs a reset"),
    "CAMERA_DOWN": N_("camera {camera} is down: {reason}"),
    "CAMERA_RECONNECTED": N_("camera {camera} reconnected ({reconnects} reconnects since start)"),
    "STORE_CONFLICT": N_("the database holds another chain: the writer stopped"),
    "STORE_DOWN": N_("the database does not take records ({pending} waiting in the journal): "
                     "{error}"),
    "STORE_FAILED": N_("a record could not be stored (the PLC got STORE_FAILED): {error}"),
    "DRIFT_WARNING": N_("camera {camera} has moved {shift_px} px since the calibration: drift "
                        "warning"),
    "DRIFT_ALARM": N_("camera {camera} has moved {shift_px} px since the calibration: drift "
                      "alarm, recalibrate"),
    "CALIBRATION_AGE": N_("the calibration (version {version}) is {age_days} days old; the "
                          "limit is {limit_days} days"),
    "STATION_DOWN": N_("the station process ended (exit code {exit_code}); it is being "
                       "restarted"),
}


def words(a: Alarm) -> str:
    """The alarm's message in the page's language, from its text key and arguments."""
    code = a.text_key.removeprefix("alarm.")
    args = {k: i18n.num(v, 1) if isinstance(v, float) else "—" if v is None else v
            for k, v in a.text_args.items()}
    try:
        if code == "NOK_STREAK":
            return ngettext("{count} NOK result in a row (recipe {recipe})",
                            "{count} NOK results in a row (recipe {recipe})",
                            int(a.text_args["count"])).format(**args)
        if code in TEXTS:
            return _(TEXTS[code]).format(**args)
    except (KeyError, ValueError, TypeError, IndexError):
        pass  # an alarm written without the arguments its message names: its own text
    return a.text


def count_words(active: int, unacknowledged: int) -> str:
    """"2 active alarms (1 unacknowledged)" in the page's language."""
    return (ngettext("{n} active alarm", "{n} active alarms", active).format(n=active) + " ("
            + _("{n} unacknowledged").format(n=unacknowledged) + ")")


@router.get("/alarms")
async def alarms_page(request: Request) -> Html:
    """Standing alarms (acknowledge) and the history (filters, pages of :data:`PAGE`)."""
    user = await page_user(request)
    if user is None:
        return to_login(request)
    form = dict(request.query_params)
    filters, problems = parse_filters(form)
    repo = request.state.services.store.alarms
    standing: list[Alarm] = await in_thread(repo.standing)
    history: list[Alarm] = await in_thread(lambda: repo.find(filters, PAGE + 1))
    e = html.esc
    body = ('<section class="panel" aria-labelledby="standing-h"><h2 id="standing-h">'
            + e(_("Standing alarms")) + '</h2><p class="muted">'
            + e(_("Active, or cleared and not yet acknowledged (ISA-18.2).")) + '</p>'
            f'<p class="msg" role="status"></p>{table(standing, user, "standing")}</section>'
            '<section class="panel" aria-labelledby="history-h"><h2 id="history-h">'
            + e(_("History")) + f'</h2>{filter_form(form, problems)}'
            f'{table(history[:PAGE], user, "history")}{next_link(form, history)}</section>')
    return HTMLResponse(html.layout(_("Alarms"), user, body, "/alarms"))


@router.get("/web/alarms/count")
async def alarm_count(request: Request) -> HTMLResponse:
    """The header's badge: how many alarms are standing (empty when none or logged out)."""
    user = await page_user(request)
    if user is None:
        return HTMLResponse("", headers={"Cache-Control": "no-store"})
    counts: AlarmCounts = await in_thread(request.state.services.store.alarms.counts)
    return HTMLResponse(badge(counts), headers={"Cache-Control": "no-store"})


def badge(c: AlarmCounts) -> str:
    """Words and a count, never colour alone: "2 alarms (1 unacknowledged)"."""
    if c.active == 0 and c.unacknowledged == 0:
        return '<span class="alarm-badge none">' + html.esc(_("no alarms")) + "</span>"
    return (f'<span class="alarm-badge {html.esc(c.highest or "low")}" data-active="{c.active}"'
            f' data-unacked="{c.unacknowledged}">⚠ '
            + html.esc(count_words(c.active, c.unacknowledged)) + "</span>")


def parse_filters(form: dict[str, str]) -> tuple[AlarmFilter, list[str]]:
    """The history's filters from the form; what is wrong is said on the page, not a 400."""
    problems: list[str] = []

    def time_of(name: str) -> datetime | None:
        text = form.get(name, "").strip()
        if not text:
            return None
        try:
            value = datetime.fromisoformat(text)
        except ValueError:
            problems.append(_("{name}: {value} is not a date and time like "
                              "2026-11-02T06:00").format(name=name, value=repr(text)))
            return None
        return value if value.tzinfo else value.replace(tzinfo=UTC)

    def choice(name: str, options: dict[str, bool | None]) -> bool | None:
        value = form.get(name, "all" if name == "state" else "any")
        if value not in options:
            problems.append(_("{name}: {value} is not one of {options}").format(
                name=name, value=repr(value), options=", ".join(options)))
            return None
        return options[value]

    priority = form.get("priority") or None
    if priority is not None and priority not in get_args(Priority):
        problems.append(_("{name}: {value} is not one of {options}").format(
            name="priority", value=repr(priority), options="high, medium, low"))
        priority = None
    before = form.get("before_id", "")
    source = form.get("source", "").strip()[:64] or None
    return AlarmFilter(
        active=choice("state", _STATES), acknowledged=choice("acknowledged", _ACKED),
        source=source, priority=priority,  # type: ignore[arg-type]
        since=time_of("since"), until=time_of("until"),
        before_id=int(before) if before.isdigit() and 0 < int(before) < 2**62 else None,
    ), problems


def filter_form(form: dict[str, str], problems: list[str]) -> str:
    def select(name: str, label: str, options: list[str], default: str) -> str:
        now = form.get(name, default)
        opts = "".join(f'<option value="{html.esc(o)}"{" selected" if o == now else ""}>'
                       f"{html.esc(_(WORDS[o or 'any']))}</option>" for o in options)
        return (f'<label for="f-{name}">{label}</label>'
                f'<select id="f-{name}" name="{name}">{opts}</select>')

    def field(name: str, label: str, hint: str) -> str:
        return (f'<label for="f-{name}">{label}</label><input id="f-{name}" name="{name}" '
                f'value="{html.esc(form.get(name, ""))}" placeholder="{html.esc(hint)}">')

    errors = "".join(f"<li>{html.esc(p)}</li>" for p in problems)
    return ('<form id="alarm-filters" class="filters" method="get" action="/alarms">'
            + select("state", html.esc(_("State")), list(_STATES), "all")
            + select("acknowledged", html.esc(_("Acknowledged")), list(_ACKED), "any")
            + select("priority", html.esc(_("Priority")), ["", *get_args(Priority)], "")
            + field("source", html.esc(_("Source")), _("link: or camera:left1"))
            + field("since", html.esc(_("Raised from")), "2026-11-02T06:00")
            + field("until", html.esc(_("Raised before")), "2026-11-02T14:00")
            + '<button type="submit">' + html.esc(_("Filter")) + "</button></form>"
            + (f'<div class="form-errors" role="alert"><ul>{errors}</ul></div>'
               if problems else ""))


def table(alarms: list[Alarm], user: Principal, kind: str) -> str:
    if not alarms:
        return f'<p class="muted" id="{kind}-empty">' + html.esc(_("No alarms.")) + "</p>"
    may_ack = user.role.allows(Role.OPERATOR)
    rows = "".join(row(a, may_ack) for a in alarms)
    heads = "".join(f'<th scope="col">{html.esc(_(h))}</th>' for h in (
        N_("Priority"), N_("Raised"), N_("Source"), N_("Alarm"), N_("State"), N_("Cleared"),
        N_("Acknowledged")))
    return (f'<table class="alarms" id="{kind}-alarms"><thead><tr>{heads}</tr></thead>'
            f"<tbody>{rows}</tbody></table>")


def row(a: Alarm, may_ack: bool) -> str:
    text = words(a)
    if a.acked_at is not None:
        ack = f"{html.esc(a.acked_by)}, {html.when(a.acked_at)}"
    elif may_ack:
        label = _("acknowledge alarm {id}: {text}").format(id=a.id, text=text)
        ack = (f'<button class="post ack" type="button" data-reload="1" '
               f'data-action="/api/v1/alarms/{a.id}/acknowledge" '
               f'aria-label="{html.esc(label)}">' + html.esc(_("Acknowledge")) + "</button>")
    else:
        ack = html.esc(_("not yet"))
    state = "active" if a.active else "cleared"
    return (f'<tr data-id="{a.id}" data-code="{html.esc(a.code)}" data-state="{state}" '
            f'class="{"acked" if a.acknowledged else "unacked"}">'
            f'<td class="prio {html.esc(a.priority)}">{html.esc(_(WORDS[a.priority]))}</td>'
            f'<td>{html.when(a.raised_at)}</td><td>{html.esc(a.source)}</td>'
            f'<td><b>{html.esc(a.code)}</b> {html.esc(text)}</td>'
            f'<td class="alarm-state">{html.esc(_(WORDS[state]))}</td>'
            f'<td>{html.when(a.cleared_at)}</td>'
            f'<td class="ack">{ack}</td></tr>')


def next_link(form: dict[str, str], history: list[Alarm]) -> str:
    if len(history) <= PAGE:
        return ""
    query: dict[str, Any] = {**form, "before_id": history[PAGE - 1].id}
    return (f'<p><a id="older" href="/alarms?{html.esc(urlencode(query))}">'
            + html.esc(_("older alarms")) + "</a></p>")
