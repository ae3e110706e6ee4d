"""Calibration verify: the taught reference part measured again, on any link's command.

The verify is a trigger like any other (the station's thread, pipeline and record), with the
part id :data:`VERIFY_PART_ID`: that record is the verify record in the audit trail. Its pose
is then judged against the active recipe's taught pose (:func:`server.drift.judge_reference`):
the 6-DoF difference, and pass or fail against the recipe's grasp tolerances. A verify needs a
recipe measured in one trigger; it is refused while a teach is armed (the teach would take the
verify's result as the new reference).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from drivers.links.base import LinkRequest, VerifyOutcome
from mvpose_core.reasons import Reason
from server.drift import VERIFY_PART_ID, VerifyReport, judge_reference
from server.errors import ConflictError

if TYPE_CHECKING:
    from server.station.core import Station
    from server.station.recorder import Answer


async def verify_now(station: Station, link: str, by: str
                     ) -> tuple[VerifyOutcome, VerifyReport | None, Answer | None]:
    """Measure the reference part and judge it: the link's outcome, the report (None: no
    verdict, the outcome's code says why) and the trigger's answer (None: not measured)."""
    active = station.active
    if active is None:
        return VerifyOutcome(int(Reason.UNKNOWN_RECIPE), 0,
                             message="verify: the station has no recipe selected"), None, None
    if station.measuring.teach_armed_by is not None:
        return VerifyOutcome(int(Reason.BUSY), 0, message=(
            f"verify: a teach armed by {station.measuring.teach_armed_by!r} waits for the next "
            "result; trigger it first")), None, None
    views = sorted({s.view for s in active.config.sightings})
    if len(views) > 1:
        return VerifyOutcome(int(Reason.BAD_ARGUMENT), 0, message=(
            f"verify: recipe {active.config.name!r} measures in views {views}; a verify "
            "measures a recipe of one trigger")), None, None
    request = LinkRequest(link=link, trigger_id=0, view_index=0, robot_pose=None,
                          part_id=VERIFY_PART_ID, recipe=0)
    answer = await station.measure_answer(request)
    out = answer.outcome
    rec = answer.record
    if rec is None or rec.T_rf_from_pf is None:
        code = out.result_code or int(Reason.INTERNAL_ERROR)
        return VerifyOutcome(code, out.result_id, message=(
            f"verify: the reference part was not measured ({answer.message})")), None, answer
    try:
        report = judge_reference(rec, active.config, active.version, answer.db_id,
                                 out.result_id)
    except ConflictError as err:
        return VerifyOutcome(int(Reason.BAD_INPUT), out.result_id, message=str(err)), None, answer
    return VerifyOutcome(
        0, out.result_id, passed=report.passed, difference=tuple(report.offset.values),
        displacement_mm=report.grasp_displacement_mm, rotation_deg=report.rotation_deg,
        limit_mm=report.limit_mm, limit_deg=report.limit_deg, message=report.message,
    ), report, answer
