"""The FastAPI application of the API process: create_app(settings, station) and its lifespan.

The store, image archive and metrics open in the lifespan (in a worker thread: migrations block)
and are yielded as typed state; endpoints reach them through the Annotated dependencies of
server/api/deps.py. The station itself (cameras, links, pipeline) runs in the station process;
this app reaches it through ``station``, the control channel's client
(server.station.client.StationClient), kept on ``app.state.station``. Without one, the station
routes answer 503 and the read side works as ever.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from typing import Any, Protocol, TypedDict

import anyio.to_thread
from fastapi import FastAPI

from server.api import PREFIX, api_router
from server.api.problems import BodyLimitMiddleware, install_problem_handlers
from server.settings import Settings
from server.state import Services, open_services
from server.web import install as install_web


class StationHandle(Protocol):
    """What the API needs of the station process (server.station.client.StationClient)."""

    def readiness(self) -> Mapping[str, bool]:
        """Named checks for /health/ready, e.g. {"station": True, "cameras": True}."""
        ...

    def status(self) -> dict[str, Any]:
        ...


class AppState(TypedDict):
    services: Services


def create_app(settings: Settings, station: StationHandle | None = None) -> FastAPI:
    """The station's API app; nothing is opened until the lifespan starts."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[AppState]:
        # The station process seeds the recipes; this process only reads them.
        services = await anyio.to_thread.run_sync(
            lambda: open_services(settings, seed=station is None))
        try:
            yield {"services": services}
        finally:
            await anyio.to_thread.run_sync(services.close)

    app = FastAPI(
        title="mvpose station server",
        version=settings.resolved_software_version,
        summary="Multi-view 6-DoF pose of car-body parts: results, audit trail, recipes.",
        lifespan=lifespan,
        docs_url=None,  # served by server.web from the swagger-ui-dist package (offline)
        redoc_url=None,
    )
    app.state.station = station
    install_problem_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    app.include_router(api_router(), prefix=PREFIX)
    install_web(app)  # the operator page and /docs
    return app
