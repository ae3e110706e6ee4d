"""Operator page: Live, History (list, drill-down, export links) and the downscaled frames."""

from __future__ import annotations

from datetime import datetime
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response, StreamingResponse

from mvpose_core.offset import frame_offsets
from mvpose_core.station import RecipeConfig
from server.auth import Role
from server.errors import InvalidInputError, NotFoundError
from server.store.schemas import MAX_ID, MeasurementFilter
from server.web import html, i18n
from server.web.context import (
    VERIFY_ENDPOINT,
    TeachPreview,
    deadline_ms,
    has_endpoint,
    in_thread,
    live_feed,
    need,
    page_user,
    reader_of,
    render_live_result,
    render_status,
    station_up,
)
from server.web.i18n import N_, _
from server.web.reader import Reader, RecordView

router = APIRouter(include_in_schema=False, dependencies=[Depends(i18n.page_language)])
Html = Response  # HTMLResponse or a RedirectResponse to the login


def to_login(request: Request) -> RedirectResponse:
    return RedirectResponse(f"/login?next={request.url.path}", status_code=303)


# ---------------------------------------------------------------------------- Live
@router.get("/")
async def live_page(request: Request) -> Html:
    user = await page_user(request)
    if user is None:
        return to_login(request)
    reader = reader_of(request)
    newest = await in_thread(reader.newest_id)
    result, frames, _framed, _complete = await in_thread(render_live_result, reader, newest, None)
    status = await in_thread(render_status, request.app, reader)
    actions = ""
    if html.can(user, Role.OPERATOR):
        up = await in_thread(station_up, request.app)
        down = disabled_down(up)
        e = html.esc
        confirm = _("The next OK result becomes the active recipe's reference (zero offset). "
                    "Arm?")
        actions = """<section class="panel actions"><h2>""" + e(_("Commissioning")) + """</h2>
<form id="trigger-form" data-action="/web/actions/trigger"><label>""" + e(_("part id")) + f"""
<input name="part_id" maxlength="40"></label><button type="submit" data-needs-station{down}>
""" + e(_("Trigger now")) + f"""</button></form>
<button type="button" class="post" data-needs-station
 data-action="/web/actions/arm-teach" data-confirm="{e(confirm)}"
 {down}>""" + e(_("Arm teach")) + """</button><p class="msg" role="status"></p></section>"""
    body = f"""<div id="live" data-events="/web/live/events" class="grid">
<div class="col">{status}{result}{actions}</div><div class="col wide">{frames}</div></div>"""
    return HTMLResponse(html.layout(_("Live"), user, body, "/"))


def disabled_down(up: bool) -> str:
    """The attributes of a station action while the station is down."""
    return "" if up else " disabled title='" + html.esc(_('station down')) + "'"


@router.get("/web/live/events")
async def live_events(request: Request) -> StreamingResponse:
    await need(request, Role.READ)
    return StreamingResponse(live_feed(request).stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-store", "X-Accel-Buffering": "no"})


# ---------------------------------------------------------------------------- frames
@router.get("/web/frames/{measurement_id}/{view}/{camera_id}")
async def frame(
    request: Request,
    measurement_id: Annotated[int, Path(ge=1, le=MAX_ID)],
    view: Annotated[int, Path(ge=1, le=255)],
    camera_id: Annotated[str, Path(max_length=64)],
    w: Annotated[int, Query(ge=64, le=4096)] = html.FRAME_WIDTH,
) -> Response:
    """An archived frame downscaled to ``w`` px wide, as JPEG (frames never change)."""
    await need(request, Role.READ)
    return await frame_response(request, measurement_id, view, camera_id, w)


async def frame_response(request: Request, measurement_id: int, view: int, camera_id: str,
                         w: int) -> Response:
    services = request.state.services

    def load() -> bytes:
        for i in services.store.images.for_measurement(measurement_id):
            if i.view == view and i.camera_id == camera_id and i.evicted_at is None:
                img = cv2.imread(str(services.images.resolve(i.path)), cv2.IMREAD_UNCHANGED)
                if img is None:
                    break
                if img.shape[1] > w:
                    h = round(img.shape[0] * w / img.shape[1])
                    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
                good, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 85])
                if good:
                    return bytes(np.asarray(buf).tobytes())
        raise NotFoundError(f"measurement {measurement_id} has no archived frame of view {view} "
                            f"camera {camera_id!r}")

    body = await in_thread(load)
    return Response(body, media_type="image/jpeg",
                    headers={"Cache-Control": "private, max-age=86400"})


# ---------------------------------------------------------------------------- History
FILTERS = ("since", "until", "result", "reason_code", "recipe", "part_id")


@router.get("/history")
async def history_page(
    request: Request,
    since: Annotated[str, Query(max_length=64)] = "",
    until: Annotated[str, Query(max_length=64)] = "",
    result: Literal["OK", "NOK", ""] = "",
    reason_code: Annotated[str, Query(max_length=5, pattern=r"^\d*$")] = "",
    recipe: Annotated[str, Query(max_length=64)] = "",
    part_id: Annotated[str, Query(max_length=64)] = "",
    cursor: Annotated[str | None, Query(max_length=200)] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    fragment: bool = False,
) -> Html:
    """The list with the REST API's filters and cursor paging; export links for the same."""
    user = await page_user(request)
    if user is None:
        return to_login(request)
    reader = reader_of(request)
    params = {"since": since, "until": until, "result": result,
              "reason_code": reason_code, "recipe": recipe, "part_id": part_id}
    status = 200
    try:
        # A form sends its empty fields too: empty means "any", as an absent REST parameter.
        filters = MeasurementFilter(since=_time(since, "since"), until=_time(until, "until"),
                                    result=result or None,
                                    reason_code=int(reason_code) if reason_code else None,
                                    recipe=recipe or None, part_id=part_id or None)
        items, next_cursor = await in_thread(reader.store.measurements.summary_page, filters,
                                             cursor, limit)
    except InvalidInputError as err:
        # The page says what is wrong where the list would be (htmx swaps a 400 in: app.js).
        status = 400
        rows = ('<div id="rows"><p class="msg error" role="alert">'
                + html.esc(_("Not filtered:")) + f' {html.esc(err.detail)}</p></div>')
    else:
        next_url = (f"/history?{html.query(params | {'cursor': next_cursor, 'limit': limit})}"
                    if next_cursor else None)
        rows = html.history_rows(items, next_url, html.query(params))
    if fragment:
        return HTMLResponse(rows, status_code=status)
    e = html.esc
    sel = {v: " selected" if result == v else "" for v in ("", "OK", "NOK")}
    body = """<section class="panel"><h2>""" + e(_("History")) + """</h2>
<form id="filters" class="filters" action="/history" method="get" hx-get="/history"
 hx-target="#rows" hx-select="#rows" hx-swap="outerHTML" hx-push-url="true">
<label>""" + e(_("since")) + f""" <input name="since" value="{e(params['since'])}"
 placeholder="2026-11-02T06:00Z"></label>
<label>""" + e(_("until")) + f""" <input name="until" value="{e(params['until'])}"></label>
<label>""" + e(_("result")) + f""" <select name="result">
<option value=""{sel[""]}>""" + e(_("any")) + f"""</option>
<option value="OK"{sel["OK"]}>{html.ok_word()}</option>
<option value="NOK"{sel["NOK"]}>{html.nok_word()}</option></select></label>
<label>""" + e(_("reason code")) + f""" <input name="reason_code" type="number" min="0" max="65535"
 value="{e(reason_code)}"></label>
<label>""" + e(_("recipe")) + f""" <input name="recipe" value="{e(recipe)}"></label>
<label>""" + e(_("part id")) + f""" <input name="part_id" value="{e(part_id)}"></label>
<label>""" + e(_("per page")) + f""" <input name="limit" type="number" min="1" max="1000"
 value="{limit}"></label>
<button type="submit">""" + e(_("Filter")) + f"""</button></form>{rows}</section>"""
    return HTMLResponse(html.layout(_("History"), user, body, "/history"), status_code=status)


def _time(text: str, name: str) -> datetime | None:
    if not text:
        return None
    try:
        t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise InvalidInputError(_("{name} = {text} is not an ISO 8601 time").format(
            name=name, text=repr(text))) from None
    if t.tzinfo is None:
        raise InvalidInputError(_("{name} = {text} has no time zone; add Z or +hh:mm").format(
            name=name, text=repr(text)))
    return t


@router.get("/history/{measurement_id}")
async def record_page(
    request: Request, measurement_id: Annotated[int, Path(ge=1, le=MAX_ID)]
) -> Html:
    """One record: result, images with overlays, residuals, timings, versions; teach from it."""
    user = await page_user(request)
    if user is None:
        return to_login(request)
    reader = reader_of(request)
    view: RecordView = await in_thread(reader.get, measurement_id)
    s, rec = view.stored, view.stored.record
    teach = ""
    if html.can(user, Role.OPERATOR) and rec.result == "OK":
        preview = await in_thread(teach_preview, reader, view)
        teach = teach_block(s.id, preview, await in_thread(station_up, request.app))
        if has_endpoint(request.app, VERIFY_ENDPOINT, "post"):
            teach += verify_block(s.id)
    e = html.esc
    images = "".join(
        "<li>" + e(_("view {view} {camera}: {state}").format(
            view=i.view, camera=i.camera_id,
            state=_("archived") if (i.view, i.camera_id) in view.frames else _("evicted")))
        + "</li>" for i in rec.images) or (
        "<li>" + e(_('none kept (OK frames are kept 1 in N)')) + "</li>")
    body = """<div class="grid"><div class="col">
""" + html.result_panel(s.id, rec, deadline_ms(reader), N_("Measurement")) + """
<section class="panel"><h2>""" + e(_("Audit")) + """</h2>
<dl><dt>""" + e(_("seq")) + f"""</dt><dd>{s.seq}</dd>
<dt>""" + e(_("stored")) + f"""</dt><dd>{html.when(s.stored_at)}</dd>
<dt>""" + e(_("hash")) + f"""</dt><dd class="hash">{e(s.hash)}</dd>
<dt>""" + e(_("recipe")) + f"""</dt><dd><a href="/recipes/{e(rec.recipe)}">{e(rec.recipe)}</a>
 v{rec.recipe_version}</dd>
<dt>""" + e(_("calibration")) + """</dt>
<dd>""" + e(rec.calibration_id or _('station file')) + f"""
 {e((rec.calibration_hash or '')[:12])}</dd>
<dt>""" + e(_("software")) + f"""</dt><dd>{e(rec.software_version)}</dd></dl>
<h3>""" + e(_("Timings")) + f"""</h3>{html.timings_table(rec)}
<h3>""" + e(_("Frames")) + f"""</h3><ul>{images}</ul>
</section>{teach}
</div><div class="col wide"><section class="panel" id="frames" data-id="{s.id}">
<h2>""" + e(_("Images and overlays")) + f"""</h2>{html.legend()}<div class="cams">\
{html.camera_figures(view)}</div>
<h3>""" + e(_("Detections and residuals")) + f"""</h3>{html.detections_table(view)}
</section></div></div>"""
    title = _("Measurement {id}").format(id=s.id)
    return HTMLResponse(html.layout(title, user, body, "/history"))


def teach_preview(reader: Reader, view: RecordView) -> TeachPreview | None:
    """The offset between the active reference and this measurement's pose: what the taught
    path moves by when this measurement becomes the reference."""
    rec = view.stored.record
    active = reader.active_recipe_of(rec.recipe)
    if active is None or rec.T_rf_from_pf is None:
        return None
    recipe: RecipeConfig = active
    off = frame_offsets(np.array(rec.T_rf_from_pf), recipe.T_rf_from_pf0.matrix,
                        recipe.T_pf_from_grasp.matrix, recipe.robot_convention)
    return TeachPreview(recipe, [float(v) for v in off.base], off.grasp_displacement_mm,
                        off.rotation_deg)


def verify_block(rec_id: int) -> str:
    e = html.esc
    return """<section class="panel"><h2>""" + e(_("Verify the calibration")) + """</h2>
<p>""" + e(_("If this is a measurement of the taught reference part, the calibration still holds "
        "when its implied offset is within the recipe's 1σ tolerances.")) + f"""</p>
<button type="button" class="post" data-action="{VERIFY_ENDPOINT}"
 data-body='{{"measurement_id": {rec_id}}}'>
""" + e(_("Verify with this reference measurement")) + """\
</button>
<p class="msg" role="status"></p></section>"""


def teach_block(rec_id: int, p: TeachPreview | None, station_up: bool) -> str:
    if p is None:
        return ""
    conv = p.recipe.robot_convention
    cells = "".join(f"<td>{html.num(v)} {html.esc(u)}</td>"
                    for v, u in zip(p.values, html.units(conv), strict=True))
    heads = "".join(f"<th>{html.esc(x)}</th>" for x in conv.labels)
    down = disabled_down(station_up)
    e = html.esc
    note = ("" if station_up else
            "<p class='muted'>" + e(_('station down: teaching needs the station')) + "</p>")
    return """<section class="panel"><h2>""" + e(_("Teach")) + f"""</h2>
<button type="button" id="teach-open" data-needs-station{down}>\
""" + e(_("Teach this as the reference…")) + f"""</button>{note}
<dialog id="teach-dialog"><h3>""" + e(_("Make measurement #{id} the reference of {recipe}?").format(
        id=rec_id, recipe=p.recipe.name)) + """</h3>
<p>""" + e(_("Against the active reference (v{version}) this part sits at the offset below. After "
        "teaching, a part lying like this one reads zero offset; the robot's taught path must "
        "be re-touched for the new reference.").format(version=p.recipe.version)) + """</p>
<table class="offset" id="teach-offset"><caption>\
""" + e(_("implied offset, {convention} convention").format(
        convention=conv.value)) + f"""</caption>\
<tr>{heads}</tr><tr>{cells}</tr></table>
<p>""" + e(_("grasp point moves {mm} mm, part turns {deg}°").format(
        mm=html.num(p.grasp_displacement_mm), deg=html.num(p.rotation_deg))) + """</p>
<form method="dialog"><button value="cancel">""" + e(_("Cancel")) + f"""</button>
<button type="button" class="post" data-action="/web/actions/teach"
 data-body='{{"measurement_id": {rec_id}}}'>""" + e(_("Teach")) + """</button></form>
<p class="msg" role="status"></p></dialog></section>"""
