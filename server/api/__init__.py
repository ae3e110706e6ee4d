"""The REST API under /api/v1, one module per domain."""

from __future__ import annotations

from fastapi import APIRouter

from server.api import (
    alarms,
    drift,
    gauge,
    handeye,
    health,
    measurements,
    metrics,
    station,
    tokens,
    users,
    versions,
)
from server.api.openapi import problem_responses

PREFIX = "/api/v1"


def api_router() -> APIRouter:
    router = APIRouter()
    for sub in (
        measurements.router,
        versions.recipes_router,
        versions.calibrations_router,
        tokens.router,
        users.router,
        health.router,
        metrics.router,
    ):
        router.include_router(sub)
    # What the station process can refuse (server.station.client): an unknown measurement or
    # recipe, a busy station (server/api/openapi.py adds 401/403/422/503 and the rest).
    router.include_router(station.router, responses=problem_responses(404, 409))
    router.include_router(gauge.router, responses=problem_responses(404))
    # Verify names a measurement that may not exist or have no pose, or measures through the
    # station (503 without one).
    router.include_router(drift.router, responses=problem_responses(404, 409))
    router.include_router(alarms.router, responses=problem_responses(404))
    # A hand-eye step the station refuses is a 409 naming its code (503 without a station).
    router.include_router(handeye.router, responses=problem_responses(409))
    return router
