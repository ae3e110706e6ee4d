"""Station endpoints: status, commissioning trigger, teach reference, recipe selection, and a
rehearsal's move of the simulated part.

They go to the station process through its control channel (``app.state.station``); with the
station down they answer 503 while the rest of the API keeps serving history.
"""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Request
from pydantic import BaseModel, Field

from drivers.links.result import ResultEvent
from server.api.deps import (
    EngineerUser,
    IdInt,
    OperatorUser,
    ReadUser,
    Uint32,
    VersionInt,
    ViewInt,
    need_station,
)
from server.auth import Role, authorize
from server.store.schemas import MeasurementRecord

router = APIRouter(prefix="/station", tags=["station"])


class TriggerBody(BaseModel):
    part_id: str | None = Field(None, max_length=40, pattern=r"^[\x20-\x7e]*$")
    view: ViewInt = Field(0, description="0 = every camera (fixed station)")
    trigger_id: Uint32 | None = Field(
        None, description="echoed in the record (e.g. a commissioning run's "
        "own numbering, so `mvpose validate` can match results to truth); default 0")


class TriggerAnswer(BaseModel):
    result_code: int
    reason: str
    message: str
    final: bool
    views_done: int
    processing_ms: float
    result_id: int = Field(description="the record's seq: what a link publishes as result id")
    offset: list[float] | None = Field(
        description="the offset in the recipe's robot convention, full precision (null unless "
        "OK)")
    measurement_id: int | None
    record: MeasurementRecord | None
    event: ResultEvent | None = Field(
        None, description="the recorded answer as every outlet shows it (null: not recorded, "
        "e.g. an intermediate view)")


class TeachBody(BaseModel):
    measurement_id: IdInt | None = Field(
        None,
        description="teach from this stored OK measurement; omitted: the next one")


class RecipeBody(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9_.\-]+$", max_length=64)
    version: VersionInt | None = Field(None,
                                       description="activate this stored version first")


class RehearsalPart(BaseModel):
    offset: list[Annotated[float, Field(ge=-1e4, le=1e4, allow_inf_nan=False)]] = Field(
        min_length=6, max_length=7,
        description="where to put the simulated part: its offset from the active recipe's "
        "reference in the recipe's robot convention (6 values; ABB: 7, X Y Z and a quaternion), "
        "i.e. what the station should then measure")


@router.get("/status")
def status(request: Request, _user: ReadUser) -> dict[str, Any]:
    """State, cameras, links, active recipe, counters and the last result."""
    return need_station(request.app).status().model_dump(mode="json")


@router.post("/trigger")
def trigger(request: Request, user: OperatorUser,
            body: Annotated[TriggerBody | None, Body()] = None) -> TriggerAnswer:
    """Measure now, as a link's trigger would (commissioning): same thread, same record."""
    from mvpose_core.reasons import reason_name

    body = body or TriggerBody(part_id=None, view=0, trigger_id=None)
    out = need_station(request.app).trigger(part_id=body.part_id, view_index=body.view,
                                            trigger_id=body.trigger_id)
    return TriggerAnswer(
        result_code=out.result_code, reason=reason_name(out.result_code),
        message=out.message, final=out.final, views_done=out.views_done,
        processing_ms=out.processing_ms, result_id=out.result_id, offset=out.offset,
        measurement_id=out.measurement_id, record=out.record, event=out.event,
    )


@router.post("/teach")
def teach(request: Request, user: OperatorUser,
          body: Annotated[TeachBody | None, Body()] = None) -> dict[str, Any]:
    """Teach the active recipe's reference (zero offset) from a measurement: a new version."""
    station = need_station(request.app)
    body = body or TeachBody(measurement_id=None)
    if body.measurement_id is None:
        armed = station.arm_teach(user.name)
        return {"armed": True, "recipe": armed.recipe}
    rec = station.teach_from_measurement(body.measurement_id, user.name)
    return {"armed": False, **rec.model_dump(mode="json")}


@router.post("/recipe")
def select_recipe(request: Request, user: OperatorUser,
                  body: Annotated[RecipeBody, Body()]) -> dict[str, Any]:
    """Select the recipe the station measures; with a version (engineer only), activate that
    stored version first."""
    if body.version is not None:  # activating a version is a change, as under /recipes
        authorize(user, Role.ENGINEER)
    rec = need_station(request.app).activate_recipe(body.name, body.version, user.name)
    return rec.model_dump(include={"name", "version", "number", "sha256"})


@router.post("/rehearsal/part")
def rehearsal_part(request: Request, _user: EngineerUser,
                   body: Annotated[RehearsalPart, Body()]) -> dict[str, Any]:
    """Rehearsal on simulated cameras: move the simulated part (409 with real cameras)."""
    return need_station(request.app).move_part(body.offset).model_dump(mode="json")
