"""Operator page: SPC (control charts), Calibration health (with the drift detector's warnings)
and Recipes."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse

from mvpose_core.shifts import time_zone
from server.auth import Role
from server.errors import DomainError, InvalidInputError
from server.store.schemas import MeasurementFilter
from server.web import html, i18n
from server.web.context import (
    DRIFT_ENDPOINT,
    VERIFY_ENDPOINT,
    deadline_ms,
    has_endpoint,
    in_thread,
    need,
    page_user,
    reader_of,
    station_up,
)
from server.web.handeye import handeye_panel
from server.web.i18n import N_, _, ngettext
from server.web.pages import Html, disabled_down, to_login
from server.web.reader import age_words
from server.web.spc import BASELINE_POINTS, Baseline, spc_charts

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])
NamePath = Annotated[str, Path(pattern=r"^[A-Za-z0-9_.\-]+$", max_length=64)]
#: newest records on the charts unless the page asks for another number
TREND_POINTS = 2000
#: most records a chart page reads (the SPC charts compute on all, draw at most spc.DRAWN per
#: chart); 100,000 took minutes to read (docs/operator-page.md, "SPC")
MAX_POINTS = 20_000
Limit = Annotated[int, Query(ge=1, le=MAX_POINTS)]


def _zone(reader: Any) -> str:
    station = reader.services.station
    return station.time_zone if station is not None else "UTC"


@router.get("/web/trends.json")
async def trends_json(
    request: Request,
    since: datetime | None = None,
    until: datetime | None = None,
    result: Literal["OK", "NOK"] | None = None,
    recipe: Annotated[str | None, Query(max_length=64)] = None,
    limit: Limit = TREND_POINTS,
) -> dict[str, Any]:
    """Columns (oldest first) and the tolerances of the active recipe (Calibration health)."""
    await need(request, Role.READ)
    reader = reader_of(request)
    filters = MeasurementFilter(since=since, until=until, result=result, recipe=recipe)
    cols = await in_thread(reader.trends, filters, limit)
    active = await in_thread(reader.active_recipe)
    tol = html.recipe_tolerances(active[2] if active else None, deadline_ms(reader))
    return {"columns": cols, "tolerances": tol, "time_zone": _zone(reader)}


@router.get("/web/spc.json")
async def spc_json(
    request: Request,
    since: datetime | None = None,
    until: datetime | None = None,
    recipe: Annotated[str | None, Query(max_length=64)] = None,
    limit: Limit = TREND_POINTS,
    baseline: Annotated[int, Query(ge=2, le=MAX_POINTS)] = BASELINE_POINTS,
    baseline_since: datetime | None = None,
    baseline_until: datetime | None = None,
) -> dict[str, Any]:
    """I-MR charts per offset axis and camera residual: limits from the baseline, run rules'
    points, Cp/Cpk and Pp/Ppk over the window (the newest ``limit`` results)."""
    await need(request, Role.READ)
    if baseline_since and baseline_until and (baseline_since.tzinfo is None) != (
            baseline_until.tzinfo is None):
        raise InvalidInputError(_("baseline_since and baseline_until: give both with a UTC "
                                  "offset or both without (the plant's time)"))
    if baseline_since and baseline_until and baseline_until < baseline_since:
        raise InvalidInputError(_("baseline_until {until} is before baseline_since {since}").format(
            until=baseline_until.isoformat(), since=baseline_since.isoformat()))
    reader = reader_of(request)
    zone = time_zone(_zone(reader))
    # a baseline typed on the page (datetime-local) is the plant's wall-clock time
    b_since, b_until = (None if d is None else d if d.tzinfo else d.replace(tzinfo=zone)
                        for d in (baseline_since, baseline_until))
    filters = MeasurementFilter(since=since, until=until, recipe=recipe)
    cols = await in_thread(reader.trends, filters, limit)
    active = await in_thread(reader.active_recipe)
    tol = html.recipe_tolerances(active[2] if active else None, deadline_ms(reader))
    base = Baseline(baseline, b_since, b_until)
    charts = await in_thread(spc_charts, cols, tol, base)
    return {"points": len(cols["t"]), "time_zone": _zone(reader), "baseline": base.words(),
            "recipe": f"{active[0]} v{active[1]}" if active else None, "charts": charts}


def _charts_page(title: str, active: str, intro: str, kind: str, user: Any, zone: str,
                 extra: str = "", src: str = "/web/trends.json", more: str = "") -> HTMLResponse:
    e = html.esc
    body = f"""<section class="panel"><h2>{e(title)}</h2>{intro}
<form id="trend-filters" class="filters"><label>""" + e(_("points")) + f""" <input name="limit"
 type="number" min="1" max="{MAX_POINTS}" value="{TREND_POINTS}"></label><label>\
""" + e(_("recipe")) + f""" <input name="recipe"></label>{more}
<button type="submit">""" + e(_("Show")) + f"""\
</button></form>
<div id="charts" data-kind="{kind}" data-src="{src}" data-tz="{html.esc(zone)}"></div>
</section>{extra}"""
    return HTMLResponse(html.layout(title, user, body, active))


@router.get("/trends")
async def trends_page(request: Request) -> RedirectResponse:
    """The SPC page's old name."""
    query = f"?{request.url.query}" if request.url.query else ""
    return RedirectResponse(f"/spc{query}", status_code=307)


@router.get("/spc")
async def spc_page(request: Request) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    zone = _zone(reader_of(request))
    e = html.esc
    intro = "<p>" + e(_(
        "Individuals and moving-range (I-MR) charts of the newest results, oldest on the left, "
        "per offset axis, per camera's RMS residual and for the cycle time. The control limits "
        "(UCL, centre, LCL: x̄ ± 3·MR̄/1.128) come from the baseline: the first {n} points of "
        "the window unless a baseline time range is given. Dashed grey lines are the active "
        "recipe's tolerances (the deadline for the cycle time). Points that break a run rule "
        "(Nelson's eight; rules 1, 2, 5 and 6 are the Western Electric rules) are marked and "
        "listed under their chart. Cp/Cpk use σ within (MR̄/1.128), Pp/Ppk the overall σ, over "
        "all points of the window. Times are the plant's ({zone}).").format(
        n=BASELINE_POINTS, zone=zone)) + "</p>"
    more = ('<label>' + e(_("baseline points")) + f' <input name="baseline" type="number" min="2" '
            f'max="{MAX_POINTS}" value="{BASELINE_POINTS}"></label>'
            f'<label>' + e(_("or baseline from")) + ' <input name="baseline_since" '
            'type="datetime-local"></label><label>' + e(_("to")) + ' <input name="baseline_until" '
            'type="datetime-local"></label>')
    return _charts_page(_("SPC"), "/spc", intro, "spc", user, zone, src="/web/spc.json",
                        more=more)


@router.get("/calibration")
async def calibration_page(request: Request) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    reader = reader_of(request)
    ages = await in_thread(calibration_ages, reader)
    drift_mounted = has_endpoint(request.app, DRIFT_ENDPOINT, "get")
    e = html.esc
    loading = e(_("loading the drift detector's warnings…"))
    drift = (f'<div id="drift" data-src="{DRIFT_ENDPOINT}" data-loading="1"><p class="muted">'
             f"{loading}</p></div>" if drift_mounted else
             '<div id="drift" data-src=""><p class="hook">' + e(_(
                 "The drift watch is not installed in this server (no GET {endpoint}): the "
                 "charts above show what the records hold. A steady mean residual that walks "
                 "away from zero is a camera that moved.").format(endpoint=DRIFT_ENDPOINT))
             + "</p></div>")
    drift += "<p>" + e(_(
        "To check the calibration against the taught reference part: put the reference part at "
        "its taught place and verify (operator; the PLC runs the same verify with command "
        "VERIFY), or open a stored measurement of it in History and use {button}.")).format(
        button="<i>" + e(_('Verify with this reference measurement')) + "</i>") + "</p>"
    if html.can(user, Role.OPERATOR) and has_endpoint(request.app, VERIFY_ENDPOINT, "post"):
        up = await in_thread(station_up, request.app)
        down = disabled_down(up)
        drift += (f'<button type="button" class="post" data-needs-station{down} '
                  f'data-action="{VERIFY_ENDPOINT}">'
                  + e(_("Measure the reference part and verify"))
                  + '</button><p class="msg" role="status"></p>')
    handeye = await handeye_panel(request.app, user)
    extra = """<section class="panel"><h2>""" + e(_("Drift warnings")) + f"""</h2>{drift}</section>
<section class="panel"><h2>""" + e(_("Calibration age")) + f"""</h2>{ages}</section>""" + handeye
    intro = "<p>" + e(_(
        "Per camera, the mean reprojection residual of each result (du, dv in px: the marks' "
        "detected minus reprojected centres) and its RMS. A calibration that has stopped "
        "fitting shows as a mean that leaves zero and stays away.")) + "</p>"
    return _charts_page(_("Calibration health"), "/calibration", intro, "calibration", user,
                        _zone(reader), extra)


def calibration_ages(reader: Any) -> str:
    store, now = reader.store, datetime.now(UTC)
    rows = []
    for n in store.versions.names("calibration"):
        for v in store.versions.versions("calibration", n.name):
            rows.append(f"<tr><td>{html.esc(n.name)}</td><td>v{v.version}</td>"
                        f"<td>{html.when(v.created_at)}</td><td>{age_words(v.created_at, now)}"
                        f"</td><td>" + (html.esc(_('active')) if v.active else '') + f"</td>"
                        f"<td>{html.esc(v.created_by)}</td></tr>")
    station = reader.services.settings.station
    file_age = ""
    if station is not None and station.exists():
        mtime = datetime.fromtimestamp(station.stat().st_mtime, UTC)
        file_age = "<p>" + html.esc(_(
            "The cameras' intrinsics and poses come from the station file {file}, changed "
            "{when} ({age} ago).")).format(file=f"<code>{html.esc(station)}</code>",
                                            when=html.when(mtime),
                                            age=f"<b class='age'>{age_words(mtime, now)}</b>"
                                            ) + "</p>"
    heads = "".join("<th>" + html.esc(_(h)) + "</th>" for h in (
        N_("calibration"), N_("version"), N_("uploaded"), N_("age"), N_("state"), N_("by")))
    table = (f"<table><tr>{heads}</tr>{''.join(rows)}</table>" if rows else
             "<p class='muted'>" + html.esc(_('No calibration uploaded to the store.')) + "</p>")
    return file_age + table


# ---------------------------------------------------------------------------- Recipes
@router.get("/recipes")
async def recipes_page(request: Request) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    reader = reader_of(request)
    names = await in_thread(reader.store.versions.names, "recipe")
    rows = "".join(f'<tr><td><a href="/recipes/{html.esc(n.name)}">{html.esc(n.name)}</a></td>'
                   f"<td>v{n.active_version or '—'}</td><td>v{n.latest_version}</td></tr>"
                   for n in names)
    e = html.esc
    body = ('<section class="panel"><h2>' + e(_("Recipes")) + '</h2><table><tr>'
            '<th>' + e(_("recipe")) + '</th><th>' + e(_("active")) + '</th>'
            '<th>' + e(_("latest")) + f'</th></tr>'
            f"{rows}</table></section>")
    return HTMLResponse(html.layout(_("Recipes"), user, body, "/recipes"))


@router.get("/recipes/{name}")
async def recipe_page(
    request: Request, name: NamePath,
    a: Annotated[int | None, Query(ge=1, le=2**31 - 1)] = None,
    b: Annotated[int | None, Query(ge=1, le=2**31 - 1)] = None,
) -> Html:
    """Versions of one recipe, two side by side (what changed), activate, arm teach."""
    user = await page_user(request)
    if user is None:
        return to_login(request)
    reader = reader_of(request)
    versions = await in_thread(reader.store.versions.versions, "recipe", name)
    numbers = [v.version for v in versions]
    active = next((v.version for v in versions if v.active), numbers[-1])
    b = b or (numbers[-1] if numbers[-1] != active else active)
    a = a or (active if active != b else (numbers[-2] if len(numbers) > 1 else b))
    try:
        (ia, ca), (ib, cb) = await in_thread(_two, reader, name, a, b)
    except DomainError as err:
        ia = ib = None
        ca = cb = {}
        diff = f"<p class='bad'>{html.esc(err.detail)}</p>"
    else:
        diff = diff_table(ca, cb, ia.version, ib.version)
    e = html.esc
    engineer = html.can(user, Role.ENGINEER)
    up = html.can(user, Role.OPERATOR) and await in_thread(station_up, request.app)
    rows = []
    for v in versions:
        act = ""
        if engineer and not v.active:
            act = (f'<button type="button" class="post" data-action="/web/actions/activate" '
                   f"data-body='{{\"name\": \"{html.esc(name)}\", \"version\": {v.version}}}' "
                   'data-confirm="' + e(_("Activate {name} v{version}: the station measures "
                                          "with it from the next trigger on?").format(
                       name=name, version=v.version)) + '">' + e(_("Activate")) + '</button>')
        rows.append(f"<tr class='{'active' if v.active else ''}'><td>v{v.version}</td>"
                    f"<td>{html.when(v.created_at)}</td><td>{e(v.created_by)}</td>"
                    f"<td>{e(v.comment)}</td><td class='hash'>{e(v.sha256[:12])}</td>"
                    f"<td>" + (e(_('active')) if v.active else '') + f"</td><td>{act}</td></tr>")
    options = {k: "".join(f"<option{' selected' if n == sel else ''}>{n}</option>"
                          for n in numbers) for k, sel in (("a", a), ("b", b))}
    arm = ""
    if html.can(user, Role.OPERATOR):
        down = disabled_down(up)
        confirm = _("The next OK result becomes the reference of the active recipe. Arm?")
        rest = e(_("or teach from a stored OK measurement: open it in {history}.")).format(
            history='<a href="/history?result=OK">' + e(_("History")) + '</a>')
        arm = (f'<p><button type="button" class="post" data-needs-station '
               f'data-action="/web/actions/arm-teach" '
               f'data-confirm="{e(confirm)}"{down}>'
               + e(_("Arm teach (next OK result)")) + f'</button> '
               f"{rest}</p>")
    heads = "".join("<th>" + e(_(h)) + "</th>" for h in (
        N_("version"), N_("created"), N_("by"), N_("comment"), N_("sha256"), N_("state"),
        N_("action")))
    title = _("Recipe {name}").format(name=name)
    body = f"""<section class="panel"><h2>{e(title)}</h2>
<table class="versions"><tr>{heads}</tr>{''.join(rows)}</table>{arm}
<p class="msg" role="status"></p></section>
<section class="panel"><h2>""" + e(_("Side by side")) + """</h2><form class="filters" method="get">
<label>""" + e(_("left")) + f""" <select name="a">{options['a']}</select></label>
<label>""" + e(_("right")) + f""" <select name="b">{options['b']}</select></label>\
<button>""" + e(_("Compare")) + f"""</button></form>
{diff}</section>"""
    return HTMLResponse(html.layout(title, user, body, "/recipes"))


def _two(reader: Any, name: str, a: int, b: int) -> tuple[Any, Any]:
    return (reader.store.versions.content("recipe", name, a),
            reader.store.versions.content("recipe", name, b))


def flatten(obj: Any, prefix: str = "") -> dict[str, str]:
    """``{"tolerances.max_rms_px": "1.0", "marks[0].id": "T1", ...}``: one row per leaf."""
    out: dict[str, str] = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out |= flatten(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, list) and obj and any(isinstance(x, dict | list) for x in obj):
        for i, v in enumerate(obj):
            out |= flatten(v, f"{prefix}[{i}]")
    else:
        out[prefix] = str(obj) if not isinstance(obj, list) else ", ".join(map(str, obj))
    return out


def diff_table(a: dict[str, Any], b: dict[str, Any], va: int, vb: int) -> str:
    fa, fb = flatten(a), flatten(b)
    keys = sorted(set(fa) | set(fb))
    changed = [k for k in keys if fa.get(k) != fb.get(k)]
    same = [k for k in keys if fa.get(k) == fb.get(k)]
    head = "<tr><th>" + html.esc(_('field')) + f"</th><th>v{va}</th><th>v{vb}</th></tr>"

    def rows(ks: list[str], cls: str) -> str:
        return "".join(f"<tr class='{cls}'><td>{html.esc(k)}</td><td>{html.esc(fa.get(k, '—'))}"
                       f"</td><td>{html.esc(fb.get(k, '—'))}</td></tr>" for k in ks)

    summary = _("{changed} of {total} fields differ between v{a} and v{b}.").format(
        changed=len(changed), total=len(keys), a=va, b=vb)
    same_words = ngettext("{n} field the same", "{n} fields the same", len(same)).format(
        n=len(same))
    return (f"<p class='diffsum'>{html.esc(summary)}</p><table class='diff'>{head}"
            f"{rows(changed, 'changed')}</table>"
            f"<details class='same'><summary>{html.esc(same_words)}</summary>"
            f"<table class='diff'>{head}{rows(same, 'same')}</table></details>")


