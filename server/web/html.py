"""HTML of the operator page: the layout and the parts the pages and the live feed share.

Plain functions returning strings; every value from a record or a request goes through
:func:`esc`. Coordinates in the overlays are full-resolution camera pixels (the SVG's viewBox is
the camera's image size), so what the page draws is what the record says, scaled by the browser.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from datetime import UTC, datetime
from html import escape
from typing import Any
from urllib.parse import urlencode

from mvpose_core.reasons import describe
from mvpose_core.shifts import ShiftWindow, time_zone
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import RobotConvention
from server.auth import Principal, Role
from server.store.schemas import MeasurementRecord, MeasurementSummary
from server.store.shifts import ShiftCounts
from server.web.geometry import CameraOverlay
from server.web.reader import RecordView

#: residual vectors are drawn magnified so the largest is about this share of the image width
RESIDUAL_SHARE = 0.06
#: width in px of the downscaled frames on the Live page and in the drill-down
FRAME_WIDTH = 640

# What a robot convention's six (seven) numbers are measured in.
_UNITS = {
    RobotConvention.FANUC: ("mm",) * 3 + ("°",) * 3,
    RobotConvention.YASKAWA: ("mm",) * 3 + ("°",) * 3,
    RobotConvention.KUKA: ("mm",) * 3 + ("°",) * 3,
    RobotConvention.ABB: ("mm",) * 3 + ("",) * 4,
    RobotConvention.UR: ("m",) * 3 + ("rad",) * 3,
}

TABS = [("/", "Live"), ("/line", "Line"), ("/history", "History"), ("/spc", "SPC"),
        ("/calibration", "Calibration"), ("/recipes", "Recipes"), ("/gauge", "Gauge")]


def esc(x: object) -> str:
    return escape("" if x is None else str(x), quote=True)


def units(convention: RobotConvention) -> tuple[str, ...]:
    return _UNITS[convention]


def when(t: datetime | None) -> str:
    if t is None:
        return "—"
    return t.astimezone(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


def num(x: float | None, digits: int = 3) -> str:
    if x is None or not math.isfinite(x):
        return "—"
    return f"{x:.{digits}f}"


def layout(title: str, user: Principal | None, body: str, active: str = "",
           scripts: Iterable[str] = (), body_class: str = "") -> str:
    """A whole page; its one ``<h1>`` is ``title`` (shown in the header bar)."""
    on = ' class="on" aria-current="page"'
    tabs = "".join(f'<a href="{href}"{on if href == active else ""}>{esc(name)}</a>'
                   for href, name in TABS) if user else ""
    who = (f'<span class="who">{esc(user.name)} · <b data-role="{esc(user.role.value)}">'
           f'{esc(user.role.value)}</b></span>'
           f'<button class="link" id="logout" type="button">log out</button>') if user else ""
    # A logged-in page reports its user's actions and leaves when the session ends.
    scripts = [*scripts, "/static/session.js"] if user else list(scripts)
    extra = "".join(f'<script src="{esc(s)}" defer></script>' for s in scripts)
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><link rel="icon" href="/favicon.ico">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{esc(title)} · mvpose</title>
<link rel="stylesheet" href="/static/app.css">
<link rel="stylesheet" href="/static/vendor/uPlot.min.css">
<script src="/static/vendor/htmx.min.js" defer></script>
<script src="/static/vendor/uPlot.iife.min.js" defer></script>
<script src="/static/app.js" defer></script>{extra}
</head><body{f' class="{esc(body_class)}"' if body_class else ""}>
<header><span class="brand">mvpose</span><h1>{esc(title)}</h1><nav>{tabs}</nav>{who}</header>
<main>{body}</main>
<footer>mvpose operator page · <a href="/docs">API docs</a></footer>
</body></html>"""


# ---------------------------------------------------------------------------- station status
def status_panel(status: Mapping[str, Any] | None, error: str | None,
                 calibration: str, counts: str) -> str:
    """Station state, link state, active recipe and calibration (runtime.status()); the
    shift's counts (``counts``, from the store: they survive a restart of either process)."""
    if status is None:
        why = esc(error or "no station process is connected to this API process")
        return (f'<section id="status" class="panel down"><h2>Station</h2>'
                f'<p class="state bad" data-state="DOWN">station down</p><p class="why">{why}'
                f'</p><p>History, SPC charts and recipes below are read from the store.</p>'
                f'<dl><dt>Calibration</dt><dd>{calibration}</dd>'
                f'<dt>This shift</dt><dd class="counts">{counts}</dd></dl></section>')
    recipe = status.get("recipe") or {}
    links = status.get("links") or ({"plc": status["plc"]} if status.get("plc") else {})
    linked = "; ".join(f"{name}: {link_words(v)}" for name, v in links.items()) or "none"
    cal = status.get("calibration")
    if isinstance(cal, Mapping) and cal.get("id"):
        calibration = f"{esc(cal['id'])} ({esc(str(cal.get('sha256', ''))[:12])})"
    cams = status.get("cameras") or {}
    cam_rows = "".join(f"<li>{esc(k)}: {esc(_short(v))}</li>" for k, v in cams.items())
    state = str(status.get("state", "?"))
    armed = ('<p class="armed">teach armed: the next OK result becomes the reference</p>'
             if status.get("teach_armed") else "")
    rec = (f"{esc(recipe.get('name'))} v{esc(recipe.get('version'))}" if recipe else "none")
    return f"""<section id="status" class="panel">
<h2>Station {esc(status.get("station", ""))}</h2>
<p class="state" data-state="{esc(state)}">{esc(state)}</p>
<dl><dt>Link</dt><dd>{esc(linked)}</dd>
<dt>Recipe</dt><dd>{rec}</dd><dt>Calibration</dt><dd>{calibration}</dd>
<dt>This shift</dt><dd class="counts">{counts}</dd></dl>
{f"<ul class='cams'>{cam_rows}</ul>" if cam_rows else ""}{armed}</section>"""


def link_words(v: object) -> str:
    """A link's status in words: its state, and whether its PLC is online."""
    if not isinstance(v, Mapping):
        return str(v)
    state = v.get("state") or ("running" if v.get("running") else "not running")
    online = v.get("plc_online")
    return str(state) + ("" if online is None else (" · PLC online" if online
                                                    else " · PLC offline"))


def _short(v: object) -> str:
    if isinstance(v, Mapping):
        return ", ".join(f"{k} {v2}" for k, v2 in list(v.items())[:4])
    return str(v)


def shift_span(window: ShiftWindow, zone: str) -> str:
    """``early 06:00–14:00 UTC``: the shift's name and hours in plant time."""
    tz = time_zone(zone)
    return (f"{esc(window.name)} {window.start.astimezone(tz):%H:%M}–"
            f"{window.end.astimezone(tz):%H:%M} {esc(zone)}")


def shift_words(window: ShiftWindow, counts: ShiftCounts, zone: str) -> str:
    """``early 06:00–14:00 UTC: OK 41 · NOK 2 · yield 95.3 %``."""
    y = counts.yield_pct
    return (f'{shift_span(window, zone)}: OK <b data-count="ok">{counts.ok}</b> · NOK '
            f'<b data-count="nok">{counts.nok}</b> · yield {"—" if y is None else f"{y:.1f} %"}')


# ---------------------------------------------------------------------------- one result
def result_words(rec: MeasurementRecord | MeasurementSummary) -> str:
    words = describe(rec.reason_code)
    return f"{words}: {rec.message}" if rec.message and rec.result != "OK" else words


def offset_table(rec: MeasurementRecord | MeasurementSummary) -> str:
    """The offset the robot got; a NOK's measured offset (kept for diagnosis) is shown struck
    through under the words that it was not sent."""
    if rec.offset is None:
        return '<p class="muted">no offset (NOK results send none)</p>'
    conv = rec.offset.convention
    sent = rec.result == "OK"
    cls, caption = (("offset", f"offset, {esc(conv.value)} convention") if sent else
                    ("offset not-sent", f"<b>NOT SENT to the robot</b> ({esc(rec.result)}): "
                     f"the measured offset, {esc(conv.value)} convention, for diagnosis only"))
    heads = "".join(f"<th>{esc(lab)}</th>" for lab in conv.labels)
    cells = "".join(
        f'<td data-axis="{esc(lab)}">{num(v, 3 if u in ("mm", "°", "") else 5)} {esc(u)}</td>'
        for lab, v, u in zip(conv.labels, rec.offset.values, units(conv), strict=True))
    return (f'<table class="{cls}" data-sent="{str(sent).lower()}"><caption>{caption}</caption>'
            f"<tr>{heads}</tr><tr>{cells}</tr></table>")


def result_panel(rec_id: int, rec: MeasurementRecord, deadline_ms: float | None) -> str:
    ok = rec.result == "OK"
    sigma = (f"{num(rec.uncertainty.sigma_mm)} mm, {num(rec.uncertainty.sigma_deg, 4)}°"
             if rec.uncertainty else "—")
    total = rec.timings_ms.get("total")
    cycle = f"{num(total, 1)} ms" + (f" (deadline {num(deadline_ms, 0)} ms)"
                                     if deadline_ms else "")
    return f"""<section id="result" class="panel {'ok' if ok else 'nok'}" data-id="{rec_id}"
 data-trigger="{rec.trigger_id}">
<h2>Last result <a href="/history/{rec_id}">#{rec_id}</a></h2>
<p class="verdict"><b>{esc(rec.result)}</b> · {esc(rec.reason)} ({rec.reason_code})</p>
<p class="words">{esc(result_words(rec))}</p>
{offset_table(rec)}
<dl><dt>1σ at the grasp point</dt><dd>{sigma}</dd>
<dt>Cycle time</dt><dd>{cycle}</dd>
<dt>Part</dt><dd>{esc(rec.part_id or "—")} · trigger {rec.trigger_id}
 · {when(rec.triggered_at)}</dd>
<dt>Recipe</dt><dd>{esc(rec.recipe)} v{rec.recipe_version}</dd>
<dt>Calibration</dt><dd>{esc(rec.calibration_id or "station file")}</dd></dl></section>"""


# ---------------------------------------------------------------------------- frames
def frames_panel(view: RecordView | None, framed: RecordView | None) -> str:
    """The newest record's cameras (``view``); when it kept no frames, a link to the newest
    record that did (``framed``), whose images belong to another result and are not shown."""
    if view is None:
        return ('<section id="frames" class="panel"><h2>Images</h2><p class="muted">No result '
                "yet.</p></section>")
    s = view.stored
    note = ""
    if not view.has_frames and not s.record.images:
        older = (f' The newest images are of <a href="/history/{framed.stored.id}">record '
                 f"#{framed.stored.id}</a> ({esc(framed.stored.record.result)}, "
                 f"{when(framed.stored.record.triggered_at)})." if framed is not None and
                 framed.stored.id != s.id else "")
        note = (f'<p class="which">This result kept no frames (NOK frames are always kept, OK '
                f"frames 1 in N): its marks are drawn on grey.{older}</p>")
    return (f'<section id="frames" class="panel" data-id="{s.id}" data-frames="{len(view.frames)}">'
            f'<h2>Images of <a href="/history/{s.id}">#{s.id}</a> ({esc(s.record.result)})</h2>'
            f"{note}{legend()}<div class='cams'>{camera_figures(view)}</div></section>")


def legend() -> str:
    return ('<p class="legend"><span class="k found">○ found mark</span> '
            '<span class="k missing">× missing mark</span> '
            '<span class="k window">▭ predicted search window</span> '
            '<span class="k residual">→ residual, magnified (factor under each image)</span></p>')


def camera_figures(view: RecordView) -> str:
    planned = {(i.view, i.camera_id) for i in view.stored.record.images}
    return "".join(
        camera_figure(view.stored.id, ov, view.frames.get((ov.view, ov.camera_id)) is not None,
                      "frame not in the archive (being written, or evicted)"
                      if (ov.view, ov.camera_id) in planned else "no frame kept for this result")
        for ov in view.overlays)


def camera_figure(rec_id: int, ov: CameraOverlay, has_frame: bool,
                  why: str = "frame not archived") -> str:
    W, H = ov.width, ov.height
    found = sum(m.found for m in ov.marks)
    img = (f'<img src="/web/frames/{rec_id}/{ov.view}/{esc(ov.camera_id)}?w={FRAME_WIDTH}" '
           f'alt="camera {esc(ov.camera_id)} view {ov.view}" width="{FRAME_WIDTH}" '
           f'height="{round(FRAME_WIDTH * H / W)}">' if has_frame else
           f'<div class="noframe">{esc(why)}</div>')
    k = magnification(ov)
    return f"""<figure class="cam" data-view="{ov.view}" data-camera="{esc(ov.camera_id)}"
 data-width="{W}" data-height="{H}" data-magnify="{k}"><div class="frame"
 style="aspect-ratio:{W}/{H}">{img}{overlay_svg(ov, k)}</div><figcaption>{esc(ov.camera_id)}
 · view {ov.view} · {found}/{len(ov.marks)} marks · RMS {num(ov.rms_px)} px · residuals
 ×{k}</figcaption></figure>"""


def magnification(ov: CameraOverlay) -> int:
    """A round factor (1, 2, 5 × 10^n) that draws the largest residual at about
    :data:`RESIDUAL_SHARE` of the image width."""
    largest = max((math.hypot(*r) for r in ov.residuals), default=0.0)
    if largest <= 0:
        return 1
    want = RESIDUAL_SHARE * ov.width / largest
    decade = 10 ** math.floor(math.log10(want))
    return int(max(f * decade for f in (1, 2, 5) if f * decade <= want)) if want >= 1 else 1


def overlay_svg(ov: CameraOverlay, k: int) -> str:
    parts = []
    r = max(ov.width, ov.height) / 110
    for m in ov.marks:
        mid = esc(m.mark_id)
        if m.window is not None:
            u0, v0, u1, v1 = m.window
            parts.append(f'<rect class="window" data-mark="{mid}" x="{u0:.2f}" y="{v0:.2f}" '
                         f'width="{u1 - u0:.2f}" height="{v1 - v0:.2f}"/>')
        if m.found and m.uv is not None:
            u, v = m.uv
            parts.append(f'<circle class="found" data-mark="{mid}" data-u="{u:.3f}" '
                         f'data-v="{v:.3f}" cx="{u:.3f}" cy="{v:.3f}" r="{r:.1f}"/>')
            parts.append(f'<text x="{u + 1.3 * r:.1f}" y="{v - 1.3 * r:.1f}">{mid}</text>')
            res = m.residual
            if res is not None:
                parts.append(
                    f'<line class="residual" data-mark="{mid}" data-du="{res[0]:.4f}" '
                    f'data-dv="{res[1]:.4f}" x1="{u:.3f}" y1="{v:.3f}" '
                    f'x2="{u + k * res[0]:.3f}" y2="{v + k * res[1]:.3f}"/>')
        else:
            at = m.reprojected or m.predicted
            if at is not None:
                u, v = at
                parts.append(
                    f'<g class="missing" data-mark="{mid}"><title>{mid}: '
                    f'{esc(m.reason or "not found")}</title>'
                    f'<line x1="{u - r:.1f}" y1="{v - r:.1f}" x2="{u + r:.1f}" y2="{v + r:.1f}"/>'
                    f'<line x1="{u - r:.1f}" y1="{v + r:.1f}" x2="{u + r:.1f}" y2="{v - r:.1f}"/>'
                    f'<text x="{u + 1.3 * r:.1f}" y="{v - 1.3 * r:.1f}">{mid}</text></g>')
    return (f'<svg class="overlay" viewBox="0 0 {ov.width} {ov.height}" '
            f'preserveAspectRatio="none" xmlns="http://www.w3.org/2000/svg">'
            f'{"".join(parts)}</svg>')


# ---------------------------------------------------------------------------- history
def history_rows(items: list[MeasurementSummary], next_url: str | None, filters: str) -> str:
    """The list and its export links (inside the part htmx swaps, so they follow the filters)."""
    rows = []
    for m in items:
        off = (" ".join(num(v, 2) for v in m.offset.values[:3]) if m.offset else "—")
        rows.append(
            f'<tr class="{"ok" if m.result == "OK" else "nok"}" data-id="{m.id}">'
            f'<td><a href="/history/{m.id}">#{m.id}</a></td><td>{when(m.triggered_at)}</td>'
            f"<td>{m.trigger_id}</td><td>{esc(m.part_id or '')}</td>"
            f"<td>{esc(m.recipe)} v{m.recipe_version}</td><td>{esc(m.result)}</td>"
            f'<td title="{esc(describe(m.reason_code))}">{esc(m.reason)}</td><td>{off}</td>'
            f"<td>{num(m.uncertainty.sigma_mm) if m.uncertainty else '—'}</td>"
            f"<td>{num(m.residuals.rms_px) if m.residuals else '—'}</td>"
            f"<td>{num(m.total_ms, 1)}</td></tr>")
    more = (f'<a class="more" href="{esc(next_url)}" hx-get="{esc(next_url)}&fragment=1" '
            f'hx-target="#rows" hx-swap="outerHTML" hx-push-url="{esc(next_url)}">next page →</a>'
            if next_url else '<span class="muted">last page</span>')
    empty = '<tr><td colspan="11" class="muted">no measurements match</td></tr>'
    export = "/api/v1/measurements/export?format={}" + (f"&{filters}" if filters else "")
    links = (f'<p class="export">Export every match: <a href="{esc(export.format("csv"))}" '
             f'download>CSV</a> · <a href="{esc(export.format("json"))}" download>JSON</a></p>')
    return f"""<div id="rows">{links}<table class="history"><thead><tr><th>id</th><th>triggered</th>
<th>trigger</th><th>part</th><th>recipe</th><th>result</th><th>reason</th>
<th>offset X Y Z</th><th>1σ mm</th><th>RMS px</th><th>cycle ms</th></tr></thead>
<tbody>{"".join(rows) or empty}</tbody></table><p>{more}</p></div>"""


def query(params: Mapping[str, Any]) -> str:
    return urlencode({k: v for k, v in params.items() if v not in (None, "")})


def detections_table(view: RecordView) -> str:
    rows = []
    for ov in view.overlays:
        for m in ov.marks:
            res = m.residual
            rows.append(
                f"<tr><td>{ov.view}</td><td>{esc(ov.camera_id)}</td><td>{esc(m.mark_id)}</td>"
                f"<td>{'found' if m.found else 'missing'}</td>"
                f"<td>{num(m.uv[0], 2) + ', ' + num(m.uv[1], 2) if m.uv else '—'}</td>"
                f"<td>{num(res[0]) + ', ' + num(res[1]) if res else '—'}</td>"
                f"<td>{num(math.hypot(*res)) if res else '—'}</td>"
                f"<td>{esc(m.reason or '')}</td></tr>")
    return ("<table class='dets'><thead><tr><th>view</th><th>camera</th><th>mark</th>"
            "<th>state</th><th>u, v px</th><th>residual du, dv px</th><th>|r| px</th>"
            f"<th>why</th></tr></thead><tbody>{''.join(rows)}</tbody></table>")


def timings_table(rec: MeasurementRecord) -> str:
    cells = "".join(f"<tr><td>{esc(k)}</td><td>{num(v, 2)} ms</td></tr>"
                    for k, v in rec.timings_ms.items())
    return f"<table class='timings'>{cells}</table>"


def data_json(obj: Any) -> str:
    """JSON for a ``<script type="application/json">`` block (no ``</script>`` breakout)."""
    return json.dumps(obj, separators=(",", ":")).replace("</", "<\\/")


def recipe_tolerances(recipe: RecipeConfig | None, deadline_ms: float | None) -> dict[str, Any]:
    if recipe is None:
        return {}
    t = recipe.tolerances
    conv = recipe.robot_convention
    return {"convention": conv.value, "labels": list(conv.labels), "units": list(units(conv)),
            "max_offset_mm": t.max_offset_mm, "max_offset_deg": t.max_offset_deg,
            "sigma_mm": t.translation_mm, "sigma_deg": t.rotation_deg,
            "max_rms_px": t.max_rms_px, "deadline_ms": deadline_ms}


def can(user: Principal, role: Role) -> bool:
    return user.role.allows(role)
