"""Liveness and readiness probes (no token: container health checks call them)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request
from sqlalchemy.exc import SQLAlchemyError

from server.api.deps import ServicesDep, station_of
from server.api.openapi import problem_responses
from server.errors import NotReadyError, StoreUnavailableError
from server.store.db import head_revision

router = APIRouter(prefix="/health", tags=["health"])


@router.get("/live")
async def live() -> dict[str, str]:
    """The process answers (the event loop is not stuck)."""
    return {"status": "alive"}


@router.get("/ready", responses=problem_responses(503))
def ready(request: Request, services: ServicesDep) -> dict[str, Any]:
    """The store answers at the newest schema and the station process (if any) reports ready."""
    checks: dict[str, Any] = {}
    try:
        revision = services.store.revision()
    except SQLAlchemyError as err:
        raise StoreUnavailableError(f"database does not answer: {type(err).__name__}") from None
    checks["database"] = services.store.dialect
    if revision != head_revision():
        raise StoreUnavailableError(
            f"schema at revision {revision!r}, expected {head_revision()!r}"
        )
    checks["schema"] = revision
    station = station_of(request.app)
    if station is not None:
        parts = dict(station.readiness())
        checks.update(parts)
        missing = sorted(k for k, ok in parts.items() if not ok)
        if missing:
            raise NotReadyError(f"not ready: {', '.join(missing)}", checks=checks)
    return {"status": "ready", "station": services.station_name, "checks": checks}
