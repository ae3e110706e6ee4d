"""Calibration health endpoints: the drift watch per camera, and the reference-part check."""

from __future__ import annotations

import threading
from typing import Annotated

from fastapi import APIRouter, Body, Depends, Request
from fastapi.responses import Response
from pydantic import BaseModel, Field

from server.api.deps import IdInt, OperatorUser, ReadUser, ServicesDep, json_response
from server.drift import DriftReport, DriftService, VerifyReport, verify_reference

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
    measurement_id: IdInt = Field(description="a measurement of the taught reference part")


@router.get("/drift", response_model=DriftReport)
def drift(_: ReadUser, service: DriftDep) -> Response:
    """Drift watch per camera: status, estimated move in px, since when, and the recent trend."""
    return json_response(service.report())


@router.post("/calibration/verify", response_model=VerifyReport)
def verify(
    body: Annotated[VerifyRequest, Body()], _: OperatorUser, services: ServicesDep
) -> VerifyReport:
    """Check a measurement of the taught reference part: its implied offset must be ~zero."""
    return verify_reference(services.store, body.measurement_id)

