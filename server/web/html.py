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

from mvpose_core.shifts import ShiftWindow
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import RobotConvention
from server.auth import Principal, Role
from server.store.schemas import MeasurementRecord, MeasurementSummary
from server.store.shifts import ShiftCounts
from server.web import i18n
from server.web.geometry import CameraOverlay
from server.web.i18n import N_, _
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

TABS = [("/", N_("Live")), ("/line", N_("Line")), ("/history", N_("History")),
        ("/spc", N_("SPC")), ("/calibration", N_("Calibration")), ("/recipes", N_("Recipes")),
        ("/gauge", N_("Gauge")),
        ("/alarms", N_("Alarms")), ("/cameras", N_("Cameras"))]


def esc(x: object) -> str:
    return escape("" if x is None else str(x), quote=True)


def units(convention: RobotConvention) -> tuple[str, ...]:
    return _UNITS[convention]


#: a moment in the plant's time and the page's locale; a number in the page's locale
when = i18n.when
num = i18n.num


def iso(t: datetime) -> str:
    """The moment for a machine (``datetime`` attributes): ISO 8601, UTC."""
    return t.astimezone(UTC).isoformat(timespec="seconds")


def language_selector() -> str:
    """The user's language (app.js keeps the choice in a cookie and reloads)."""
    cur = i18n.current().code
    options = "".join(
        f'<option value="{code}" lang="{code.replace("_", "-")}"'
        f'{" selected" if code == cur else ""}>{esc(name)}</option>'
        for code, name in i18n.LANGUAGES.items())
    return ('<select id="lang-select" class="lang" aria-label="' + esc(_("Language")) + f'" '
            f'data-cookie="{i18n.COOKIE}">{options}</select>')


def js_messages() -> str:
    """The messages app.js shows, in the page's language (server/web/jstext.py lists them),
    with the locale and the plant's time zone: app.js's ``t()`` and formatters read this."""
    from server.web.jstext import catalogue

    return (f'<script type="application/json" id="i18n">{data_json(catalogue())}</script>')


def layout(title: str, user: Principal | None, body: str, active: str = "",
           scripts: Iterable[str] = (), body_class: str = "",
           choose_language: bool | None = None) -> str:
    """A whole page; its one ``<h1>`` is ``title`` (shown in the header bar). The language
    selector is on every page of a logged-in user and where ``choose_language`` says (the
    login page); a kiosk has no control at all and speaks the plant's language."""
    on = ' class="on" aria-current="page"'
    tabs = "".join(f'<a href="{href}"{on if href == active else ""}>' + esc(_(name)) + '</a>'
                   for href, name in TABS) if user else ""
    who = (f'<span class="who">{esc(user.name)} · <b data-role="{esc(user.role.value)}">'
           f'{esc(user.role.value)}</b></span>'
           f'<button class="link" id="logout" type="button">' + esc(_("log out")) + '</button>'
           ) if user else ""
    # A logged-in page reports its user's actions and leaves when the session ends.
    scripts = [*scripts, "/static/session.js"] if user else list(scripts)
    # the standing alarms' count, loaded and refreshed by htmx (server/web/alarms.py)
    alarms = ('<a id="alarm-count" href="/alarms" aria-live="polite" hx-get="/web/alarms/count"'
              ' hx-trigger="load, every 5s"></a>') if user else ""
    extra = "".join(f'<script src="{esc(s)}" defer></script>' for s in scripts)
    shown = user is not None if choose_language is None else choose_language
    chooser = language_selector() if shown else ""
    return f"""<!doctype html>
<html lang="{i18n.current().html_lang}"><head><meta charset="utf-8">
<link rel="icon" href="/favicon.ico">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{esc(title)} · mvpose</title>
<link rel="stylesheet" href="/static/app.css">
<link rel="stylesheet" href="/static/vendor/uPlot.min.css">
<script src="/static/vendor/htmx.min.js" defer></script>
<script src="/static/vendor/uPlot.iife.min.js" defer></script>
<script src="/static/app.js" defer></script>{extra}{js_messages()}
</head><body{f' class="{esc(body_class)}"' if body_class else ""}>
<header><span class="brand">mvpose</span><h1>{esc(title)}</h1><nav>{tabs}</nav>{alarms}{who}\
{chooser}</header>
<main>{body}</main>
<footer>""" + esc(_("mvpose operator page")) + """ ·
<a href="/docs">""" + esc(_("API docs")) + """</a></footer>
</body></html>"""


# ---------------------------------------------------------------------------- station status
def status_panel(status: Mapping[str, Any] | None, error: str | None,
                 calibration: str, counts: str) -> str:
    """Station state, link state, active recipe and calibration (runtime.status()); the
    shift's counts (``counts``, from the store: they survive a restart of either process)."""
    if status is None:
        why = esc(error or _("no station process is connected to this API process"))
        store_words = esc(_("History, SPC charts and recipes below are read from the store."))
        return ('<section id="status" class="panel down"><h2>' + esc(_("Station")) + '</h2>'
                '<p class="state bad" data-state="DOWN">' + esc(_("station down")) + '</p>'
                f'<p class="why">{why}</p><p>{store_words}</p>'
                '<dl><dt>' + esc(_("Calibration")) + f'</dt><dd>{calibration}</dd>'
                '<dt>' + esc(_("This shift")) + f'</dt><dd class="counts">{counts}</dd></dl>'
                "</section>")
    recipe = status.get("recipe") or {}
    links = status.get("links") or ({"plc": status["plc"]} if status.get("plc") else {})
    linked = "; ".join(f"{name}: {link_words(v)}" for name, v in links.items()) or _("none")
    cal = status.get("calibration")
    if isinstance(cal, Mapping) and cal.get("id"):
        calibration = f"{esc(cal['id'])} ({esc(str(cal.get('sha256', ''))[:12])})"
    cams = status.get("cameras") or {}
    cam_rows = "".join(f"<li>{esc(k)}: {esc(_short(v))}</li>" for k, v in cams.items())
    state = str(status.get("state", "?"))
    armed = ('<p class="armed">'
             + esc(_("teach armed: the next OK result becomes the reference")) + '</p>'
             if status.get("teach_armed") else "")
    rec = (f"{esc(recipe.get('name'))} v{esc(recipe.get('version'))}" if recipe
           else esc(_("none")))
    return """<section id="status" class="panel">
<h2>""" + esc(_("Station {name}").format(name=status.get("station", ""))) + f"""</h2>
<p class="state" data-state="{esc(state)}">{esc(state)}</p>
<dl><dt>""" + esc(_("Link")) + f"""</dt><dd>{esc(linked)}</dd>
<dt>""" + esc(_("Recipe")) + f"""</dt><dd>{rec}</dd>
<dt>""" + esc(_("Calibration")) + f"""</dt><dd>{calibration}</dd>
<dt>""" + esc(_("This shift")) + f"""</dt><dd class="counts">{counts}</dd></dl>
{f"<ul class='cams'>{cam_rows}</ul>" if cam_rows else ""}{armed}</section>"""


def link_words(v: object) -> str:
    """A link's status in words: its state, and whether its PLC is online."""
    if not isinstance(v, Mapping):
        return str(v)
    state = v.get("state") or (_("running") if v.get("running") else _("not running"))
    online = v.get("plc_online")
    return str(state) + ("" if online is None else (" · " + _("PLC online") if online
                                                    else " · " + _("PLC offline")))


def _short(v: object) -> str:
    if isinstance(v, Mapping):
        return ", ".join(f"{k} {v2}" for k, v2 in list(v.items())[:4])
    return str(v)


def shift_span(window: ShiftWindow, zone: str) -> str:
    """``early 06:00–14:00 UTC``: the shift's name and hours in plant time (``zone``, the
    station file's; the page's language has the same)."""
    return (f"{esc(window.name)} {i18n.clock(window.start)}–{i18n.clock(window.end)} "
            f"{esc(zone)}")


def shift_words(window: ShiftWindow, counts: ShiftCounts, zone: str) -> str:
    """``early 06:00–14:00 UTC: OK 41 · NOK 2 · yield 95.3 %``."""
    return (f'{shift_span(window, zone)}: {ok_word()} <b data-count="ok">{counts.ok}</b> · '
            f'{nok_word()} <b data-count="nok">{counts.nok}</b> · ' + esc(_("yield")) + f' '
            f"{i18n.pct(counts.yield_pct)}")


def ok_word() -> str:
    """The line's word for OK (German lines say i.O.)."""
    return esc(_("OK"))


def nok_word() -> str:
    """The line's word for NOK (German lines say n.i.O.)."""
    return esc(_("NOK"))


def verdict_word(result: str) -> str:
    return ok_word() if result == "OK" else nok_word() if result == "NOK" else esc(result)


# ---------------------------------------------------------------------------- one result
def result_words(rec: MeasurementRecord | MeasurementSummary) -> str:
    words = i18n.reason_words(rec.reason_code)
    return f"{words}: {rec.message}" if rec.message and rec.result != "OK" else words


def offset_table(rec: MeasurementRecord | MeasurementSummary) -> str:
    """The offset the robot got; a NOK's measured offset (kept for diagnosis) is shown struck
    through under the words that it was not sent."""
    if rec.offset is None:
        return '<p class="muted">' + esc(_("no offset (NOK results send none)")) + '</p>'
    conv = rec.offset.convention
    sent = rec.result == "OK"
    cls, caption = (
        ("offset", esc(_("offset, {convention} convention").format(convention=conv.value)))
        if sent else
        ("offset not-sent", "<b>" + esc(_('NOT SENT to the robot')) + f"</b> "
         f"({verdict_word(rec.result)}): " + esc(_(
             "the measured offset, {convention} convention, for diagnosis only").format(
             convention=conv.value))))
    heads = "".join(f"<th>{esc(lab)}</th>" for lab in conv.labels)
    cells = "".join(
        f'<td data-axis="{esc(lab)}">{num(v, 3 if u in ("mm", "°", "") else 5)} {esc(u)}</td>'
        for lab, v, u in zip(conv.labels, rec.offset.values, units(conv), strict=True))
    return (f'<table class="{cls}" data-sent="{str(sent).lower()}"><caption>{caption}</caption>'
            f"<tr>{heads}</tr><tr>{cells}</tr></table>")


def result_panel(rec_id: int, rec: MeasurementRecord, deadline_ms: float | None,
                 heading: str = N_("Last result")) -> str:
    ok = rec.result == "OK"
    sigma = (f"{num(rec.uncertainty.sigma_mm)} mm, {num(rec.uncertainty.sigma_deg, 4)}°"
             if rec.uncertainty else "—")
    total = rec.timings_ms.get("total")
    cycle = f"{num(total, 1)} ms" + (
        " (" + _("deadline {ms} ms").format(ms=num(deadline_ms, 0)) + ")" if deadline_ms else "")
    title = esc(_(heading))
    return f"""<section id="result" class="panel {'ok' if ok else 'nok'}" data-id="{rec_id}"
 data-trigger="{rec.trigger_id}">
<h2>{title} <a href="/history/{rec_id}">#{rec_id}</a></h2>
<p class="verdict"><b>{verdict_word(rec.result)}</b> · {esc(rec.reason)} ({rec.reason_code})</p>
<p class="words">{esc(result_words(rec))}</p>
{offset_table(rec)}
<dl><dt>""" + esc(_("1σ at the grasp point")) + f"""</dt><dd>{sigma}</dd>
<dt>""" + esc(_("Cycle time")) + f"""</dt><dd>{esc(cycle)}</dd>
<dt>""" + esc(_("Part")) + f"""</dt><dd>{esc(rec.part_id or "—")}
 · """ + esc(_("trigger")) + f""" {rec.trigger_id}
 · {when(rec.triggered_at)}</dd>
<dt>""" + esc(_("Recipe")) + f"""</dt><dd>{esc(rec.recipe)} v{rec.recipe_version}</dd>
<dt>""" + esc(_("Calibration")) + """</dt>
<dd>""" + esc(rec.calibration_id or _("station file")) + """</dd></dl>
</section>"""


# ---------------------------------------------------------------------------- frames
def frames_panel(view: RecordView | None, framed: RecordView | None) -> str:
    """The newest record's cameras (``view``); when it kept no frames, a link to the newest
    record that did (``framed``), whose images belong to another result and are not shown."""
    if view is None:
        return ('<section id="frames" class="panel"><h2>' + esc(_("Images")) + '</h2>'
                '<p class="muted">' + esc(_("No result yet.")) + '</p></section>')
    s = view.stored
    note = ""
    if not view.has_frames and not s.record.images:
        older = (" " + esc(_("The newest images are of {record} ({result}, {when}).")).format(
            record=f'<a href="/history/{framed.stored.id}">'
                   + esc(_("record #{id}").format(id=framed.stored.id)) + "</a>",
            result=verdict_word(framed.stored.record.result),
            when=when(framed.stored.record.triggered_at))
            if framed is not None and framed.stored.id != s.id else "")
        note = ('<p class="which">' + esc(_(
            "This result kept no frames (NOK frames are always kept, OK frames 1 in N): its "
            "marks are drawn on grey.")) + f"{older}</p>")
    heading = esc(_("Images of {record} ({result})")).format(
        record=f'<a href="/history/{s.id}">#{s.id}</a>', result=verdict_word(s.record.result))
    return (f'<section id="frames" class="panel" data-id="{s.id}" data-frames="{len(view.frames)}">'
            f"<h2>{heading}</h2>"
            f"{note}{legend()}<div class='cams'>{camera_figures(view)}</div></section>")


def legend() -> str:
    return ('<p class="legend"><span class="k found">○ ' + esc(_("found mark")) + '</span> '
            '<span class="k missing">× ' + esc(_("missing mark")) + '</span> '
            '<span class="k window">▭ ' + esc(_("predicted search window")) + '</span> '
            '<span class="k residual">→ '
            + esc(_("residual, magnified (factor under each image)")) + '</span></p>')


def camera_figures(view: RecordView) -> str:
    planned = {(i.view, i.camera_id) for i in view.stored.record.images}
    return "".join(
        camera_figure(view.stored.id, ov, view.frames.get((ov.view, ov.camera_id)) is not None,
                      _("frame not in the archive (being written, or evicted)")
                      if (ov.view, ov.camera_id) in planned else _("no frame kept for this result"))
        for ov in view.overlays)


def camera_figure(rec_id: int, ov: CameraOverlay, has_frame: bool,
                  why: str = "") -> str:
    W, H = ov.width, ov.height
    found = sum(m.found for m in ov.marks)
    alt = _("camera {camera} view {view}").format(camera=ov.camera_id, view=ov.view)
    img = (f'<img src="/web/frames/{rec_id}/{ov.view}/{esc(ov.camera_id)}?w={FRAME_WIDTH}" '
           f'alt="{esc(alt)}" width="{FRAME_WIDTH}" '
           f'height="{round(FRAME_WIDTH * H / W)}">' if has_frame else
           '<div class="noframe">' + esc(why or _("frame not archived")) + '</div>')

    k = magnification(ov)
    caption = esc(_("{camera} · view {view} · {found}/{marks} marks · RMS {rms} px · residuals "
                    "×{k}").format(camera=ov.camera_id, view=ov.view, found=found,
                                   marks=len(ov.marks), rms=num(ov.rms_px), k=k))
    return f"""<figure class="cam" data-view="{ov.view}" data-camera="{esc(ov.camera_id)}"
 data-width="{W}" data-height="{H}" data-magnify="{k}"><div class="frame"
 style="aspect-ratio:{W}/{H}">{img}{overlay_svg(ov, k)}</div><figcaption>{caption}\
</figcaption></figure>"""


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
                    + esc(m.reason or _("not found")) + f'</title>'
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
            f'<td><a href="/history/{m.id}">#{m.id}</a></td>'
            f'<td><time datetime="{iso(m.triggered_at)}">{when(m.triggered_at)}</time></td>'
            f"<td>{m.trigger_id}</td><td>{esc(m.part_id or '')}</td>"
            f"<td>{esc(m.recipe)} v{m.recipe_version}</td>"
            f'<td data-result="{esc(m.result)}">{verdict_word(m.result)}</td>'
            f'<td title="{esc(i18n.reason_words(m.reason_code))}">{esc(m.reason)}</td>'
            f"<td>{off}</td>"
            f"<td>{num(m.uncertainty.sigma_mm) if m.uncertainty else '—'}</td>"
            f"<td>{num(m.residuals.rms_px) if m.residuals else '—'}</td>"
            f"<td>{num(m.total_ms, 1)}</td></tr>")
    more = (f'<a class="more" href="{esc(next_url)}" hx-get="{esc(next_url)}&fragment=1" '
            f'hx-target="#rows" hx-swap="outerHTML" hx-push-url="{esc(next_url)}">'
            + esc(_("next page")) + ' →</a>'
            if next_url else '<span class="muted">' + esc(_("last page")) + '</span>')
    empty = '<tr><td colspan="11" class="muted">' + esc(_("no measurements match")) + '</td></tr>'
    export = "/api/v1/measurements/export?format={}" + (f"&{filters}" if filters else "")
    links = ('<p class="export">' + esc(_("Export every match:")) + f' '
             f'<a href="{esc(export.format("csv"))}" download>CSV</a> · '
             f'<a href="{esc(export.format("json"))}" download>JSON</a></p>')
    heads = "".join("<th>" + esc(_(h)) + "</th>" for h in HISTORY_HEADS)
    return f"""<div id="rows">{links}<table class="history"><thead><tr>{heads}</tr></thead>
<tbody>{"".join(rows) or empty}</tbody></table><p>{more}</p></div>"""


HISTORY_HEADS = (N_("id"), N_("triggered"), N_("trigger"), N_("part"), N_("recipe"),
                 N_("result"), N_("reason"), N_("offset X Y Z"), N_("1σ mm"), N_("RMS px"),
                 N_("cycle ms"))


def query(params: Mapping[str, Any]) -> str:
    return urlencode({k: v for k, v in params.items() if v not in (None, "")})


def detections_table(view: RecordView) -> str:
    rows = []
    for ov in view.overlays:
        for m in ov.marks:
            res = m.residual
            rows.append(
                f"<tr><td>{ov.view}</td><td>{esc(ov.camera_id)}</td><td>{esc(m.mark_id)}</td>"
                f"<td>" + esc(_('found') if m.found else _('missing')) + f"</td>"
                f"<td>{num(m.uv[0], 2) + ', ' + num(m.uv[1], 2) if m.uv else '—'}</td>"
                f"<td>{num(res[0]) + ', ' + num(res[1]) if res else '—'}</td>"
                f"<td>{num(math.hypot(*res)) if res else '—'}</td>"
                f"<td>{esc(m.reason or '')}</td></tr>")
    heads = "".join("<th>" + esc(_(h)) + "</th>" for h in (
        N_("view"), N_("camera"), N_("mark"), N_("state"), N_("u, v px"),
        N_("residual du, dv px"), N_("|r| px"), N_("why")))
    return (f"<table class='dets'><thead><tr>{heads}</tr></thead><tbody>{''.join(rows)}"
            "</tbody></table>")


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
