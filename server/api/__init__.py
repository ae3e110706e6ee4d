"""The REST API under /api/v1, one module per domain."""

from __future__ import annotations

from fastapi import APIRouter

from server.api import drift, health, measurements, metrics, tokens, versions

PREFIX = "/api/v1"


def api_router() -> APIRouter:
    router = APIRouter()
    for sub in (
        measurements.router,
        versions.recipes_router,
        versions.calibrations_router,
        tokens.router,
        health.router,
        metrics.router,
    ):
        router.include_router(sub)
    router.include_router(drift.router)
    return router
