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
from typing import Protocol, TypedDict

import anyio.to_thread
from fastapi import FastAPI

from server.api import PREFIX, api_router
from server.api.problems import BodyLimitMiddleware, install_problem_handlers
from server.settings import Settings
from server.state import Services, open_services
from server.station.messages import (
    ArmTeachAnswer,
    CameraViewAnswer,
    HandEyeAnswer,
    MovePartAnswer,
    RecipeAnswer,
    StationStatus,
    TriggerAnswer,
    VerifyAnswer,
)
from server.web import install as install_web


class StationHandle(Protocol):
    """What the API and the operator page call on the station process: every operation of
    server.station.client.StationClient they use, with the control channel's models
    (server.station.messages). A station that does not answer raises
    server.station.client.StationDownError (503), except ``readiness`` (``station: False``)
    and ``reload_recipes`` (the station reads the store when it starts)."""

    def readiness(self) -> Mapping[str, bool]:
        """Named checks for /health/ready, e.g. {"station": True, "cameras": True}."""
        ...

    def status(self) -> StationStatus:
        """The live status: state, cameras, links, recipe, counts, last result."""
        ...

    def trigger(self, part_id: str | None = None, view_index: int = 0,
                trigger_id: int | None = None) -> TriggerAnswer:
        """Measure now, as a link's trigger would (same thread, same record)."""
        ...

    def verify(self, by: str) -> VerifyAnswer:
        """Measure the taught reference part now and judge it (the verify record)."""
        ...

    def handeye(self, step: str, by: str, holdout: int | None = None,
                robot_pose: list[float] | None = None) -> HandEyeAnswer:
        """A step of the robot-driven hand-eye session: begin, pose, calculate or status."""
        ...

    def arm_teach(self, by: str) -> ArmTeachAnswer:
        """The next final OK result becomes the selected recipe's reference."""
        ...

    def teach_from_measurement(self, measurement_id: int, by: str) -> RecipeAnswer:
        """A stored OK measurement becomes the selected recipe's reference: a new version."""
        ...

    def activate_recipe(self, name: str, version: int | None, by: str) -> RecipeAnswer:
        """Select recipe ``name`` (activating its stored ``version`` first)."""
        ...

    def reload_recipes(self) -> None:
        """Measure with the versions activated in the store from the next trigger on."""
        ...

    def metrics_text(self) -> str:
        """The station process's Prometheus text, for the API's scrape."""
        ...

    def move_part(self, offset: list[float]) -> MovePartAnswer:
        """Rehearsal on simulated cameras: the part at ``offset`` from the active reference."""
        ...

    def camera_view(self, width: int = 640) -> CameraViewAnswer:
        """The live camera view's newest frames with focus and light figures."""
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
