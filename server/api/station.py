"""Station endpoints of the runtime: status, commissioning trigger, teach reference, recipe."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, Request
from pydantic import BaseModel, Field

from server.api.deps import EngineerUser, ReadUser
from server.errors import ConflictError, InvalidInputError, NotFoundError, NotReadyError
from server.store.schemas import MeasurementRecord

router = APIRouter(prefix="/station", tags=["station"])


def _runtime(request: Request) -> Any:
    runtime = getattr(request.app.state, "runtime", None)
    if runtime is None or runtime.pipeline is None:
        raise NotReadyError("the station runtime is not running")
    return runtime


class TriggerBody(BaseModel):
    part_id: str | None = Field(None, max_length=40, pattern=r"^[\x20-\x7e]*$")
    view: int = Field(0, ge=0, le=255, description="0 = every camera (fixed station)")


class TriggerAnswer(BaseModel):
    result_code: int
    reason: str
    message: str
    final: bool
    views_done: int
    processing_ms: float
    offset: list[float] = Field(description="the PLC form, 6 values (zeros when NOK)")
    measurement_id: int | None
    record: MeasurementRecord | None


class TeachBody(BaseModel):
    measurement_id: int | None = Field(
        None, ge=1, description="teach from this stored OK measurement; omitted: the next one")


class RecipeBody(BaseModel):
    name: str = Field(pattern=r"^[A-Za-z0-9_.\-]+$", max_length=64)
    version: int | None = Field(None, ge=1, description="activate this stored version first")


@router.get("/status")
def status(request: Request, _user: ReadUser) -> dict[str, Any]:
    """State, cameras, PLC link, active recipe, counters and the last result."""
    return dict(_runtime(request).status())


@router.post("/trigger")
def trigger(request: Request, user: EngineerUser,
            body: Annotated[TriggerBody | None, Body()] = None) -> TriggerAnswer:
    """Measure now, as a PLC trigger would (commissioning); the record gets trigger id 0."""
    from mvpose_core.reasons import reason_name

    runtime = _runtime(request)
    body = body or TriggerBody(part_id=None, view=0)
    try:
        result = runtime.trigger(part_id=body.part_id, view_index=body.view)
    except TimeoutError:
        raise ConflictError("the station is busy: the trigger did not run within 10 s") from None
    out = result.outcome
    return TriggerAnswer(
        result_code=out.result_code, reason=reason_name(out.result_code), message=result.message,
        final=out.final, views_done=out.views_done, processing_ms=out.processing_ms,
        offset=list(out.offset), measurement_id=result.stored.id if result.stored else None,
        record=result.record,
    )


@router.post("/teach")
def teach(request: Request, user: EngineerUser,
          body: Annotated[TeachBody | None, Body()] = None) -> dict[str, Any]:
    """Teach the active recipe's reference (zero offset) from a measurement: a new version."""
    runtime = _runtime(request)
    body = body or TeachBody(measurement_id=None)
    if body.measurement_id is None:
        runtime.arm_teach()
        return {"armed": True, "recipe": runtime.active.config.name}
    try:
        rec = runtime.teach_from_measurement(body.measurement_id, user.name)
    except KeyError as err:
        raise NotFoundError(str(err.args[0])) from None
    except ValueError as err:
        raise InvalidInputError(str(err)) from None
    return {"armed": False, "recipe": rec.config.name, "version": rec.version,
            "sha256": rec.sha256, "T_rf_from_pf0": rec.config.T_rf_from_pf0.model_dump()}


@router.post("/recipe")
def select_recipe(request: Request, user: EngineerUser,
                  body: Annotated[RecipeBody, Body()]) -> dict[str, Any]:
    """Select the recipe the station measures (and activate one of its stored versions)."""
    runtime = _runtime(request)
    try:
        rec = runtime.activate_recipe(body.name, body.version, user.name)
    except KeyError as err:
        raise NotFoundError(str(err.args[0])) from None
    return {"name": rec.config.name, "version": rec.version, "number": rec.number,
            "sha256": rec.sha256}
