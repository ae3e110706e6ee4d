"""The Calibration page's hand-eye session panel: what the robot-driven session holds, and its
begin and calculate buttons (engineer). The poses come from the robot program (PLC, OPC UA or
REST, docs/handeye-robot.md); the page follows and finishes the session."""

from __future__ import annotations

from typing import Any

from server.auth import Principal, Role
from server.web import html
from server.web.context import has_endpoint, in_thread, runtime_of

HANDEYE_ENDPOINT = "/api/v1/calibration/handeye"


def _status(app: Any) -> dict[str, Any] | None:
    """The station's session answer as a dict, None when the station is down. Blocking."""
    runtime = runtime_of(app)
    if runtime is None:
        return None
    try:
        return runtime.handeye("status", "page").model_dump(mode="json")
    except Exception:  # noqa: BLE001 - a station that cannot answer is a station that is down
        return None


async def handeye_panel(app: Any, user: Principal) -> str:
    """The panel's HTML ('' when the server has no hand-eye routes)."""
    if not has_endpoint(app, f"{HANDEYE_ENDPOINT}/begin", "post"):
        return ""
    answer = await in_thread(_status, app)
    if answer is None:
        state = "<p class='muted'>The station is down: no session to show.</p>"
    else:
        s = answer["session"]
        last = s.get("last") or {}
        if s.get("active"):
            state = (f"<p class='handeye-state'>Session on rig {html.esc(s['rig'])} "
                     f"({html.esc(', '.join(s['cameras']))}), board {html.esc(s['board'])}: "
                     f"<b>{s['poses']}</b> poses held, {s['needed']} needed "
                     f"({s['holdout']} held out to check the result); poses in the "
                     f"{html.esc(s['convention'])} convention.</p>")
        else:
            state = "<p class='handeye-state'>No session begun.</p>"
        if last.get("message"):
            state += (f"<p>Last answer: code {last['code']}: {html.esc(last['message'])}</p>")
        if last.get("version"):
            state += (f"<p>Calibration version {last['version']} waits for activation: read "
                      "its report, then activate it under Recipes and calibrations.</p>")
    buttons = ""
    if html.can(user, Role.ENGINEER) and answer is not None:
        buttons = (
            f'<button type="button" class="post" data-needs-station '
            f'data-action="{HANDEYE_ENDPOINT}/begin" data-confirm="Begin a new hand-eye '
            'session (the current one is dropped)?">Begin a session</button> '
            f'<button type="button" class="post" data-needs-station '
            f'data-action="{HANDEYE_ENDPOINT}/calculate">Calculate</button>'
            '<p class="msg" role="status"></p>')
    return (
        '<section class="panel" id="handeye"><h2>Robot-driven hand-eye</h2>'
        "<p>The robot program adds a pose at each position (PLC command HANDEYE_ADD_POSE, OPC UA "
        "HandEyeAddPose or REST); the station captures the board with every camera of the rig. "
        "The result is stored as a calibration version waiting for an engineer's activation."
        f"</p>{state}{buttons}</section>")
