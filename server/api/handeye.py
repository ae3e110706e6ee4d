"""The robot-driven hand-eye over REST (engineer): begin, add pose, calculate, and the session.

A step the station refuses (too few poses, a board not found, a unit that looks wrong ...) is a
409 problem whose ``code`` and ``code_name`` are the session's code (HandEyeCode), the same
number a PLC reads in its command result register.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Request
from pydantic import BaseModel, Field

from mvpose_core.calibration.codes import HandEyeCode
from mvpose_core.reasons import Reason
from server.api.deps import EngineerUser, ReadUser, need_station
from server.errors import ConflictError
from server.station.messages import HandEyeAnswer

router = APIRouter(prefix="/calibration/handeye", tags=["calibration"])


class BeginBody(BaseModel):
    holdout: int | None = Field(None, ge=0, le=50,
                                description="poses kept out of the solve to check it (default 3)")


class PoseBody(BaseModel):
    pose: list[float] = Field(min_length=6, max_length=7, description=(
        "the robot's actual flange pose in the selected recipe's robot convention (fanuc "
        "X,Y,Z,W,P,R mm/deg; abb X,Y,Z,q1..q4; ur m and rad)"))


def _answer(out: HandEyeAnswer) -> HandEyeAnswer:
    if out.code != 0:
        try:
            name = HandEyeCode(out.code).name
        except ValueError:  # a link's own code (BAD_ARGUMENT, ...)
            name = Reason(out.code).name if out.code in Reason._value2member_map_ else "UNKNOWN"
        raise ConflictError(out.message, code=out.code, code_name=name, poses=out.poses,
                            pose=out.pose)
    return out


@router.get("", response_model=HandEyeAnswer)
def session(request: Request, _: ReadUser) -> HandEyeAnswer:
    """The hand-eye session as it is now, with its last step's answer."""
    return need_station(request.app).handeye("status", "api")


@router.post("/begin", response_model=HandEyeAnswer)
def begin(request: Request, user: EngineerUser,
          body: Annotated[BeginBody | None, Body()] = None) -> HandEyeAnswer:
    """Begin a session (any earlier one is dropped): the station file's calibration board,
    the cameras of its robot-mounted rig."""
    holdout = body.holdout if body is not None else None
    return _answer(need_station(request.app).handeye("begin", user.name, holdout=holdout))


@router.post("/poses", response_model=HandEyeAnswer)
def add_pose(request: Request, user: EngineerUser,
             body: Annotated[PoseBody, Body()]) -> HandEyeAnswer:
    """The robot is at this flange pose: capture the board from every camera of the rig."""
    return _answer(need_station(request.app).handeye("pose", user.name,
                                                     robot_pose=list(body.pose)))


@router.post("/calculate", response_model=HandEyeAnswer)
def calculate(request: Request, user: EngineerUser) -> HandEyeAnswer:
    """Solve, check the held-out poses, and store the calibration as a version waiting for
    activation (POST /calibrations/{station}/versions/{version}/activate)."""
    return _answer(need_station(request.app).handeye("calculate", user.name))
