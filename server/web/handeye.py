"""The Calibration page's hand-eye session panel: what the robot-driven session holds, and its
begin and calculate buttons (engineer). The poses come from the robot program (PLC, OPC UA or
REST, docs/handeye-robot.md); the page follows and finishes the session."""

from __future__ import annotations

from typing import Any

from mvpose_core.calibration.codes import HandEyeCode
from server.auth import Principal, Role
from server.web import html
from server.web.context import has_endpoint, in_thread, runtime_of
from server.web.i18n import N_, _

HANDEYE_ENDPOINT = "/api/v1/calibration/handeye"
#: each answer code's words (mvpose_core.calibration.codes; a link shows the number)
CODE_WORDS = {
    HandEyeCode.OK: N_("done"),
    HandEyeCode.NO_SESSION: N_("no session begun"),
    HandEyeCode.TOO_FEW_POSES: N_("too few poses"),
    HandEyeCode.TOO_LITTLE_ROTATION: N_("too little rotation between the poses"),
    HandEyeCode.UNIT_SUSPICIOUS: N_("the poses' units look wrong"),
    HandEyeCode.BOARD_NOT_FOUND: N_("board not found"),
    HandEyeCode.OUTLIERS: N_("too many outlying poses"),
    HandEyeCode.BOARD_SCALE: N_("the board is not its declared size"),
    HandEyeCode.POSES_DO_NOT_FIT: N_("the poses do not fit"),
    HandEyeCode.BAD_POSE: N_("not a valid pose"),
    HandEyeCode.CAPTURE_FAILED: N_("a camera gave no image"),
    HandEyeCode.SESSION_FULL: N_("the session is full"),
    HandEyeCode.NOT_AVAILABLE: N_("not available on this station"),
    HandEyeCode.FAILED: N_("failed"),
}


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
    e = html.esc
    if answer is None:
        state = "<p class='muted'>" + e(_("The station is down: no session to show.")) + "</p>"
    else:
        s = answer["session"]
        last = s.get("last") or {}
        if s.get("active"):
            state = "<p class='handeye-state'>" + _(
                "Session on rig {rig} ({cameras}), board {board}: <b>{poses}</b> poses held, "
                "{needed} needed ({holdout} held out to check the result); poses in the "
                "{convention} convention.").format(
                    rig=e(s["rig"]), cameras=e(", ".join(s["cameras"])), board=e(s["board"]),
                    poses=int(s["poses"]), needed=int(s["needed"]), holdout=int(s["holdout"]),
                    convention=e(s["convention"])) + "</p>"
        else:
            state = "<p class='handeye-state'>" + e(_("No session begun.")) + "</p>"
        if last.get("message"):
            state += "<p>" + e(_("Last answer: code {code} ({name}): {message}").format(
                code=last["code"], name=code_words(last["code"]), message=last["message"]))
            state += "</p>"
        if last.get("version"):
            state += "<p>" + e(_(
                "Calibration version {version} waits for activation: read its report, then "
                "activate it under Recipes and calibrations.").format(
                    version=last["version"])) + "</p>"
    buttons = ""
    if html.can(user, Role.ENGINEER) and answer is not None:
        buttons = (
            f'<button type="button" class="post" data-needs-station '
            f'data-action="{HANDEYE_ENDPOINT}/begin" data-confirm="'
            + e(_("Begin a new hand-eye session (the current one is dropped)?")) + '">'
            + e(_("Begin a session")) + "</button> "
            f'<button type="button" class="post" data-needs-station '
            f'data-action="{HANDEYE_ENDPOINT}/calculate">' + e(_("Calculate")) + "</button>"
            '<p class="msg" role="status"></p>')
    return (
        '<section class="panel" id="handeye"><h2>' + e(_("Robot-driven hand-eye")) + "</h2><p>"
        + e(_("The robot program adds a pose at each position (PLC command HANDEYE_ADD_POSE, "
              "OPC UA HandEyeAddPose or REST); the station captures the board with every camera "
              "of the rig. The result is stored as a calibration version waiting for an "
              "engineer's activation.")) + f"</p>{state}{buttons}</section>")


def code_words(code: int) -> str:
    """A hand-eye answer code's name in the page's language (its number when unknown)."""
    try:
        return _(CODE_WORDS[HandEyeCode(code)])
    except (ValueError, KeyError):
        return str(code)
