"""The messages app.js shows (live updates, charts, the drift report), from the page's one
catalogue: the page writes them, translated, into a JSON block (html.js_messages) that app.js's
``t()`` reads, so the browser has no translation system of its own. tests/server/test_i18n.py
checks that every ``t("...")`` in app.js is listed here."""

from __future__ import annotations

from typing import Any

from server.web import i18n
from server.web.i18n import N_, _

MESSAGES = (
    N_("done"), N_("record #{id}"), N_("station down"), N_("off the scale: {bands}"),
    N_("time ({zone})"), N_("Time"),
    N_("{n} results; control limits from {baseline}; times in {zone}."),
    N_("{n} results, tolerances of {recipe}; control limits from {baseline}; times in {zone}."),
    N_("no values"), N_("UCL"), N_("centre"), N_("LCL"), N_("USL (tolerance)"),
    N_("LSL (tolerance)"), N_("run rule broken"), N_("{title}: individuals"),
    N_("moving range"), N_("{title}: moving range"),
    N_("Over the {n} points: Cp {cp}, Cpk {cpk} (σ within {sw} {unit}); Pp {pp}, Ppk {ppk} "
       "(σ overall {so} {unit})."),
    N_("No tolerance for this series: no capability."),
    N_("Rule {n}"), N_("Western Electric"), N_("1 point"), N_("{n} points"),
    N_("the newest {n}"), N_("No run rule broken."), N_("No control limits: no run rules."),
    N_("Camera {camera}: mean residual (px)"), N_("loading…"), N_("could not load: {error}"),
    N_("Drift watch: {status} — {records} records of {recipe} with calibration "
       "{calibration}."),
    N_("of the station file"), N_("No camera in warning or alarm."),
    N_("camera"), N_("status"), N_("what"), N_("move px"), N_("since"), N_("triggers"),
    N_("{n} (learning: {left} to go)"), N_("Last verify ({when}, {record}): {message}"),
    N_("No calibration verify recorded yet."), N_("drift watch: {error}"),
    N_("ok"), N_("warning"), N_("alarm"), N_("learning"),
    N_("Camera {camera}"), N_("camera {camera}, newest frame"),
    N_("focus of camera {camera} against its peak"), N_("Focus {focus} (peak {peak})"),
    N_("Focus {focus}"), N_("focus over"), N_("mean grey"), N_("saturated"), N_("dark"),
    N_("taken"), N_("Frame set {seq}, at most one every {period} s."), N_("No frames: {why}"),
    N_("mark windows"), N_("whole image"),  # a frame's focus_area (mvpose_core.image_figures)
)


def catalogue() -> dict[str, Any]:
    """The page's language (BCP 47), the plant's time zone and :data:`MESSAGES` translated."""
    cur = i18n.current()
    return {"lang": cur.html_lang, "zone": cur.zone_name,
            "messages": {m: _(m) for m in MESSAGES}}
