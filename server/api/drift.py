"""Calibration health endpoints: the drift watch per camera, and the reference-part check."""

from __future__ import annotations

import threading
from typing import Annotated

from fastapi import APIRouter, Body, Depends, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from server.api.deps import (
    IdInt,
    OperatorUser,
    ReadUser,
    ServicesDep,
    json_response,
    need_station,
)
from server.drift import DriftReport, DriftService, VerifyReport, verify_reference
from server.errors import ConflictError

router = APIRouter(tags=["calibration"])

_lock = threading.Lock()


def get_drift(request: Request, services: ServicesDep) -> DriftService:
    """The app's drift service, made on first use (it keeps its watch between requests)."""
    with _lock:
        service = getattr(request.app.state, "drift_service", None)
        if not isinstance(service, DriftService) or service.store is not services.store:
            service = DriftService(services.store, services.station)
            request.app.state.drift_service = service
        return service


DriftDep = Annotated[DriftService, Depends(get_drift)]


class VerifyRequest(BaseModel):
    measurement_id: IdInt | None = Field(
        None, description="judge this stored measurement of the taught reference part; "
        "omitted: measure the reference part now (the station's verify, recorded)")


@router.get("/drift", response_model=DriftReport)
def drift(_: ReadUser, service: DriftDep) -> Response:
    """Drift watch per camera: status, estimated move in px, since when, and the recent trend."""
    return json_response(service.report())


@router.post("/calibration/verify", response_model=VerifyReport)
def verify(
    request: Request, user: OperatorUser, services: ServicesDep,
    body: Annotated[VerifyRequest | None, Body()] = None,
) -> VerifyReport:
    """Verify the calibration: the taught reference part's implied offset must be ~zero."""
    if body is not None and body.measurement_id is not None:
        return verify_reference(services.store, body.measurement_id)
    out = need_station(request.app).verify(user.name)
    if out.report is None:
        raise ConflictError(out.message)
    return out.report

