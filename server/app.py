"""The FastAPI application: create_app(settings, runtime) and the lifespan that opens the services.

The store, image archive and metrics open in the lifespan (in a worker thread: migrations block)
and are yielded as typed state; endpoints reach them through the Annotated dependencies of
server/api/deps.py. Parts that need the station's hardware (cameras, PLC, the per-trigger
pipeline) come in as a :class:`Runtime`: its routers are mounted under /api/v1 next to ours, and
its lifespan runs inside ours, after the services are open and before they close.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Mapping, Sequence
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from typing import Protocol, TypedDict

import anyio.to_thread
from fastapi import APIRouter, FastAPI

from server.api import PREFIX, api_router
from server.api.problems import BodyLimitMiddleware, install_problem_handlers
from server.priority import TriggerFirst, TriggerFirstMiddleware
from server.settings import Settings
from server.state import Services, open_services


class Runtime(Protocol):
    """What the station runtime (cameras, PLC, pipeline) provides to the app."""

    def routers(self) -> Sequence[APIRouter]:
        """Routers mounted under /api/v1 (station status, REST trigger, teach reference)."""
        ...

    def lifespan(self, services: Services) -> AbstractAsyncContextManager[None]:
        """Open the hardware with the open services; close it on exit (runs inside the app's)."""
        ...

    def readiness(self) -> Mapping[str, bool]:
        """Named checks for /health/ready, e.g. {"cameras": True, "plc": False}."""
        ...


class AppState(TypedDict):
    services: Services


def create_app(settings: Settings, runtime: Runtime | None = None) -> FastAPI:
    """The station's app; nothing is opened until the lifespan starts."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[AppState]:
        services = await anyio.to_thread.run_sync(open_services, settings)
        try:
            if runtime is None:
                yield {"services": services}
            else:
                async with runtime.lifespan(services):
                    yield {"services": services}
        finally:
            await anyio.to_thread.run_sync(services.close)

    app = FastAPI(
        title="mvpose station server",
        version=settings.resolved_software_version,
        summary="Multi-view 6-DoF pose of car-body parts: results, audit trail, recipes.",
        lifespan=lifespan,
    )
    app.state.runtime = runtime
    install_problem_handlers(app)
    app.add_middleware(BodyLimitMiddleware, max_bytes=settings.max_body_bytes)
    gate = getattr(runtime, "gate", None)
    if isinstance(gate, TriggerFirst):  # outermost: a held request has cost nothing yet
        app.add_middleware(TriggerFirstMiddleware, gate=gate,
                           exempt=frozenset({f"{PREFIX}/health/live"}))
    app.include_router(api_router(), prefix=PREFIX)
    if runtime is not None:
        for router in runtime.routers():
            app.include_router(router, prefix=PREFIX)
    return app
