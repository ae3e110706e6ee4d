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

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse

from server.auth import Principal, Role
from server.store.alarms import Alarm, AlarmCounts, AlarmFilter, Priority
from server.web import html
from server.web.context import in_thread, page_user
from server.web.pages import Html, to_login

router = APIRouter(include_in_schema=False)
PAGE = 50  # history rows per page
_STATES = {"all": None, "active": True, "cleared": False}
_ACKED = {"any": None, "yes": True, "no": False}


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
    body = (f'<section class="panel" aria-labelledby="standing-h"><h2 id="standing-h">'
            f'Standing alarms</h2><p class="muted">Active, or cleared and not yet '
            f'acknowledged (ISA-18.2).</p><p class="msg" role="status"></p>'
            f'{table(standing, user, "standing")}</section>'
            f'<section class="panel" aria-labelledby="history-h"><h2 id="history-h">History'
            f'</h2>{filter_form(form, problems)}{table(history[:PAGE], user, "history")}'
            f'{next_link(form, history)}</section>')
    return HTMLResponse(html.layout("Alarms", user, body, "/alarms"))


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
        return '<span class="alarm-badge none">no alarms</span>'
    return (f'<span class="alarm-badge {html.esc(c.highest or "low")}" data-active="{c.active}"'
            f' data-unacked="{c.unacknowledged}">⚠ {c.active} active alarm'
            f'{"" if c.active == 1 else "s"} ({c.unacknowledged} unacknowledged)</span>')


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
            problems.append(f"{name}: {text!r} is not a date and time like 2026-11-02T06:00")
            return None
        return value if value.tzinfo else value.replace(tzinfo=UTC)

    def choice(name: str, options: dict[str, bool | None]) -> bool | None:
        value = form.get(name, "all" if name == "state" else "any")
        if value not in options:
            problems.append(f"{name}: {value!r} is not one of {', '.join(options)}")
            return None
        return options[value]

    priority = form.get("priority") or None
    if priority is not None and priority not in get_args(Priority):
        problems.append(f"priority: {priority!r} is not one of high, medium, low")
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
                       f"{html.esc(o or 'any')}</option>" for o in options)
        return (f'<label for="f-{name}">{label}</label>'
                f'<select id="f-{name}" name="{name}">{opts}</select>')

    def field(name: str, label: str, hint: str) -> str:
        return (f'<label for="f-{name}">{label}</label><input id="f-{name}" name="{name}" '
                f'value="{html.esc(form.get(name, ""))}" placeholder="{html.esc(hint)}">')

    errors = "".join(f"<li>{html.esc(p)}</li>" for p in problems)
    return (f'<form id="alarm-filters" class="filters" method="get" action="/alarms">'
            f'{select("state", "State", list(_STATES), "all")}'
            f'{select("acknowledged", "Acknowledged", list(_ACKED), "any")}'
            f'{select("priority", "Priority", ["", *get_args(Priority)], "")}'
            f'{field("source", "Source", "link: or camera:left1")}'
            f'{field("since", "Raised from", "2026-11-02T06:00")}'
            f'{field("until", "Raised before", "2026-11-02T14:00")}'
            f'<button type="submit">Filter</button></form>'
            + (f'<div class="form-errors" role="alert"><ul>{errors}</ul></div>'
               if problems else ""))


def table(alarms: list[Alarm], user: Principal, kind: str) -> str:
    if not alarms:
        return f'<p class="muted" id="{kind}-empty">No alarms.</p>'
    may_ack = user.role.allows(Role.OPERATOR)
    rows = "".join(row(a, may_ack) for a in alarms)
    return (f'<table class="alarms" id="{kind}-alarms"><thead><tr><th scope="col">Priority</th>'
            f'<th scope="col">Raised</th><th scope="col">Source</th><th scope="col">Alarm</th>'
            f'<th scope="col">State</th><th scope="col">Cleared</th>'
            f'<th scope="col">Acknowledged</th></tr></thead><tbody>{rows}</tbody></table>')


def row(a: Alarm, may_ack: bool) -> str:
    if a.acked_at is not None:
        ack = f"{html.esc(a.acked_by)}, {html.when(a.acked_at)}"
    elif may_ack:
        ack = (f'<button class="post ack" type="button" data-reload="1" '
               f'data-action="/api/v1/alarms/{a.id}/acknowledge" '
               f'aria-label="acknowledge alarm {a.id}: {html.esc(a.text)}">Acknowledge</button>')
    else:
        ack = "not yet"
    state = "active" if a.active else "cleared"
    return (f'<tr data-id="{a.id}" data-code="{html.esc(a.code)}" data-state="{state}" '
            f'class="{"acked" if a.acknowledged else "unacked"}">'
            f'<td class="prio {html.esc(a.priority)}">{html.esc(a.priority)}</td>'
            f'<td>{html.when(a.raised_at)}</td><td>{html.esc(a.source)}</td>'
            f'<td><b>{html.esc(a.code)}</b> {html.esc(a.text)}</td>'
            f'<td class="alarm-state">{state}</td><td>{html.when(a.cleared_at)}</td>'
            f'<td class="ack">{ack}</td></tr>')


def next_link(form: dict[str, str], history: list[Alarm]) -> str:
    if len(history) <= PAGE:
        return ""
    query: dict[str, Any] = {**form, "before_id": history[PAGE - 1].id}
    return f'<p><a id="older" href="/alarms?{html.esc(urlencode(query))}">older alarms</a></p>'
