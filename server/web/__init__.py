"""The operator page, served by the API process: Live, Line, History, SPC, Calibration,
Recipes, Gauge, Alarms, Cameras (the live camera view).

``install(app)`` mounts its routes (outside the OpenAPI schema) and the offline ``/docs``;
create_app calls it. The page reads the store as the REST API does and reaches the station only
through ``app.state.runtime``; see docs/operator-page.md.
"""

from __future__ import annotations

from fastapi import FastAPI

from server.web import actions, alarms, assets, cameras, gauge, line, more, pages


def install(app: FastAPI) -> None:
    """Mount the page and /docs; sessions live in this process (app.state.web_sessions)."""
    actions.install_sessions(app)
    for router in (assets.router, actions.router, pages.router, more.router, line.router,
                   gauge.router, alarms.router, cameras.router):
        app.include_router(router)
