"""The app as a service: problem responses, body limit, health, OpenAPI, runtime hook, start-up."""

from __future__ import annotations

import asyncio
import inspect
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from apps import ENGINEER, STATION1, settings
from asgi import StartupFailedError, running
from fastapi import APIRouter
from fastapi.routing import APIRoute

from server.api import api_router
from server.app import create_app
from server.store.db import head_revision

PROBLEM = "application/problem+json"
J = {"content-type": "application/json"}
V = "/api/v1/recipes/floor_panel/versions"


MALFORMED = [
    ("GET", "/api/v1/measurements?limit=0", None, {}, 422, "limit"),
    ("GET", "/api/v1/measurements?limit=abc", None, {}, 422, "limit"),
    ("GET", "/api/v1/measurements?result=MAYBE", None, {}, 422, "result"),
    ("GET", "/api/v1/measurements?since=yesterday", None, {}, 422, "since"),
    ("GET", "/api/v1/measurements?since=2026-11-02T06:00:00", None, {}, 400, "time zone"),
    ("GET", "/api/v1/measurements?cursor=%00%ff", None, {}, 400, "cursor"),
    ("GET", "/api/v1/measurements?cursor=bTotMQ", None, {}, 400, "cursor"),  # "m:-1"
    ("GET", "/api/v1/measurements/99999999999999999999999", None, {}, 422, "measurement_id"),
    ("GET", "/api/v1/measurements/abc", None, {}, 422, "measurement_id"),
    ("GET", "/api/v1/measurements/7", None, {}, 404, "measurement 7"),
    ("GET", "/api/v1/measurements/export?format=xml", None, {}, 422, "format"),
    ("GET", "/api/v1/recipes/floor_panel/versions/0", None, {}, 422, "version"),
    ("GET", "/api/v1/recipes/no..such/versions", None, {}, 404, "does not exist"),
    ("GET", "/api/v1/recipes/a%20b/versions", None, {}, 422, "name"),
    ("POST", V, b"{not json", J, 422, "JSON"),
    ("POST", V, b"[1, 2]", J, 422, "body"),
    ("POST", V, b'{"content": {"marks": "x"}}', J, 400, "not valid"),
    ("POST", V, b'{"content": {"name": "door"}}', J, 400, "door"),
    ("POST", "/api/v1/recipes/floor_panel/versions/1/activate?x=1", b"", {}, 200, None),
    ("POST", "/api/v1/calibrations/station1/versions", b'{"content": {}}', J, 400,
     "not a calibration file"),
    ("POST", "/api/v1/calibrations/cal/versions", b'{"content": {"id": "x"}}', J, 400,
     "calibration named after it"),
    ("POST", "/api/v1/tokens", b'{"name": "a b", "role": "read"}', J, 422, "name"),
    ("POST", "/api/v1/tokens", b'{"name": "x", "role": "admin"}', J, 422, "role"),
    ("DELETE", "/api/v1/tokens/nobody", None, {}, 404, "nobody"),
    ("POST", "/api/v1/recipes/floor_panel/versions", b'{"content": {"x": NaN}}', J, 400,
     "not valid"),
    ("PUT", "/api/v1/measurements", None, {}, 405, None),
    ("GET", "/api/v2/measurements", None, {}, 404, None),
    ("POST", "/api/v1/tokens", b"{}", {"content-length": "12x"}, 400, "Content-Length"),
]


@pytest.mark.parametrize(("method", "url", "body", "headers", "status", "words"), MALFORMED)
async def test_malformed_requests_get_4xx_problems(
    tmp_path: Path, method: str, url: str, body: bytes | None, headers: dict[str, str],
    status: int, words: str | None,
) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, _):
        r = await client.request(method, url, content=body, headers=headers)
        assert r.status_code == status, r.text
        if status >= 400:
            assert r.headers["content-type"] == PROBLEM
            problem = r.json()
            assert problem["status"] == status and problem["title"] and problem["type"]
            if words:
                assert words.lower() in (problem["detail"] + str(problem.get("errors"))).lower()


async def test_recipe_upload_checked_against_the_station(tmp_path: Path) -> None:
    recipe = yaml.safe_load(STATION1.read_text())["recipes"][0]
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, _):
        bad = recipe | {"sightings": [recipe["sightings"][0] | {"camera": "cam99"}]}
        r = await client.post("/api/v1/recipes/floor_panel/versions", json={"content": bad})
        assert r.status_code == 422 and "cam99" in r.json()["detail"]
        moved = recipe | {"T_rf_from_pf0": {"xyz": [1.0, 2.0, 3.0], "wpr": [0.0, 0.0, 1.0]}}
        r = await client.post("/api/v1/recipes/floor_panel/versions",
                              json={"content": moved, "comment": "re-taught"})
        assert r.status_code == 201 and r.json()["version"] == 2 and not r.json()["active"]
        r = await client.get("/api/v1/recipes/floor_panel/active")
        assert r.json()["info"]["version"] == 1
        r = await client.post("/api/v1/recipes/floor_panel/versions/2/activate")
        assert r.status_code == 200 and r.json()["active"]
        r = await client.get("/api/v1/recipes/floor_panel/active")
        assert r.json()["content"]["T_rf_from_pf0"]["xyz"] == [1.0, 2.0, 3.0]
        assert r.json()["info"]["created_by"] == "bootstrap"
        r = await client.get("/api/v1/recipes/floor_panel/versions")
        assert [(v["version"], v["active"]) for v in r.json()] == [(1, False), (2, True)]

        cal = _calibration(fx_more=1.0).model_dump(mode="json")
        r = await client.post("/api/v1/calibrations/station1/versions",
                              json={"content": cal, "activate": True})
        assert r.status_code == 201 and r.json()["active"] and len(r.json()["sha256"]) == 64
        r = await client.get("/api/v1/calibrations")
        assert r.json() == [{"kind": "calibration", "name": "station1", "latest_version": 1,
                             "active_version": 1}]
        tampered = cal | {"cameras": {"top_left": cal["cameras"]["top_left"] | {
            "intrinsics": cal["cameras"]["top_left"]["intrinsics"] | {"fx": 1.0}}}}
        r = await client.post("/api/v1/calibrations/station1/versions", json={"content": tampered})
        assert r.status_code == 400 and "does not match its sha256" in r.json()["detail"]
        alien = _calibration(fx_more=1.0, camera="cam99").model_dump(mode="json")
        r = await client.post("/api/v1/calibrations/station1/versions", json={"content": alien})
        assert r.status_code == 400 and "cam99" in r.json()["detail"]


async def test_body_limit_by_header_and_while_streaming(tmp_path: Path) -> None:
    app = create_app(settings(tmp_path, max_body_bytes=4096))
    async with running(app, ENGINEER) as (client, _):
        big = b'{"content": {"x": "' + b"a" * 5000 + b'"}}'
        r = await client.post("/api/v1/calibrations/c/versions", content=big,
                              headers=J)
        assert r.status_code == 413 and r.headers["content-type"] == PROBLEM
        assert r.json()["limit_bytes"] == 4096

        async def chunks() -> AsyncIterator[bytes]:  # no Content-Length: chunked upload
            for part in (big[:3000], big[3000:]):
                yield part

        r = await client.post("/api/v1/calibrations/c/versions", content=chunks(),
                              headers=J)
        assert r.status_code == 413
        r = await client.get("/api/v1/calibrations")
        assert r.json() == []  # nothing half-stored


async def test_health_and_openapi(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        assert (await client.get("/api/v1/health/live")).json() == {"status": "alive"}
        r = await client.get("/api/v1/health/ready")
        assert r.status_code == 200 and r.json()["checks"]["schema"] == head_revision()
        spec = (await client.get("/openapi.json")).json()
        assert "/api/v1/measurements/export" in spec["paths"]
        op = spec["paths"]["/api/v1/measurements"]["get"]
        assert op["description"].startswith("Measurements, newest first")
        assert "HTTPBearer" in spec["components"]["securitySchemes"]


def test_database_work_never_runs_on_the_event_loop() -> None:
    """Plain ``def`` endpoints and dependencies run in FastAPI's threadpool; only the loop-only
    liveness probe is ``async``, and the dependencies that only pick objects or parse the query
    (a thread hop each would cost more than they do), and the token check, which answers a
    token verified seconds ago from memory and sends any look-up to the threadpool. A coroutine
    endpoint that queried the store would block every other request for the duration of the
    query."""
    async_ok = {"live"}
    pure_deps = {"get_services", "get_store", "get_pause", "measurement_filter", "require_read",
                 "require_operator", "require_engineer", "current_principal"}
    routes = list(_api_routes(api_router()))
    assert len(routes) >= 20
    for route in routes:
        is_async = inspect.iscoroutinefunction(route.endpoint)
        assert is_async == (route.name in async_ok), route.path
        deps = list(route.dependant.dependencies)
        while deps:
            dep = deps.pop()
            deps += dep.dependencies
            name = getattr(dep.call, "__name__", "")
            if inspect.iscoroutinefunction(dep.call):
                assert name in pure_deps, (route.path, dep.call)


def _api_routes(router: APIRouter) -> Iterator[APIRoute]:
    for route in router.routes:
        if isinstance(route, APIRoute):
            yield route
        else:  # an included router (FastAPI keeps them nested)
            yield from _api_routes(route.original_router)  # type: ignore[attr-defined]


async def test_without_its_station_process_the_api_serves_history_and_says_so(
    tmp_path: Path,
) -> None:
    from server.station.client import StationClient

    station = StationClient(tmp_path / "nobody-listens.sock")  # the station process is down
    async with running(create_app(settings(tmp_path), station), ENGINEER) as (client, _):
        r = await client.get("/api/v1/health/ready")
        assert r.status_code == 503 and r.json()["checks"]["station"] is False
        assert "station" in r.json()["detail"]
        r = await client.get("/api/v1/station/status")
        assert r.status_code == 503 and "not running" in r.json()["detail"]
        r = await client.post("/api/v1/station/trigger", json={})
        assert r.status_code == 503
        assert (await client.get("/api/v1/measurements")).status_code == 200
        assert (await client.get("/api/v1/health/live")).status_code == 200
        # the scrape goes on without the station's counters, and says they are missing
        r = await client.get("/api/v1/metrics")
        assert r.status_code == 200
        assert "mvpose_station_up 0.0" in r.text and "mvpose_chain_head_seq 0.0" in r.text
        r = await client.post("/api/v1/station/rehearsal/part", json={"offset": [0.0] * 6})
        assert r.status_code == 503

async def test_a_malformed_station_file_stops_start_up(tmp_path: Path) -> None:
    data = yaml.safe_load(STATION1.read_text())
    data["cameras"][1]["intrinsics"]["fx"] = -5
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(data))
    with pytest.raises(StartupFailedError) as err:
        async with running(create_app(settings(tmp_path, station=bad))):
            pass
    text = str(err.value)
    assert str(bad) in text and "intrinsics.fx" in text and "-5" in text
    assert not (tmp_path / "var" / "mvpose.db").exists()  # refused before opening the store


async def test_requests_are_served_while_another_waits_on_the_store(tmp_path: Path) -> None:
    """A slow export stream (a worker thread) does not hold up liveness on the event loop."""
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        store = state["services"].store
        conn = store.engine.raw_connection()  # hold the write lock like a long transaction
        try:
            conn.execute("BEGIN IMMEDIATE")
            upload = asyncio.create_task(client.post(
                "/api/v1/calibrations/station1/versions",
                json={"content": _calibration(fx_more=1.0).model_dump(mode="json")}))
            live = await asyncio.wait_for(client.get("/api/v1/health/live"), timeout=30)
            assert live.status_code == 200 and not upload.done()
        finally:
            conn.rollback()
            conn.close()
        assert (await asyncio.wait_for(upload, timeout=30)).status_code == 201


async def test_an_unreachable_database_is_503_not_500(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        # the file vanishes under a running station: the next connection finds no tables
        state["services"].store.engine.dispose()
        for suffix in ("", "-wal", "-shm"):
            (tmp_path / "var" / f"mvpose.db{suffix}").unlink(missing_ok=True)
        r = await client.get("/api/v1/measurements")
        assert r.status_code == 503, r.text
        assert r.headers["content-type"] == PROBLEM and "database" in r.json()["detail"]


def _calibration(fx_more: float, camera: str = "top_left") -> Any:
    """A calibration file of station 1 whose camera ``camera`` has fx ``fx_more`` px more."""
    from mvpose_core.calibration.files import CameraCalibration, InputsSummary, make_calibration
    from mvpose_core.station import load_station

    cam = load_station(STATION1).camera("top_left").model
    measured = CameraCalibration(
        intrinsics={"fx": cam.fx + fx_more, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy},
        distortion=list(cam.dist), image_size=(cam.width, cam.height))
    return make_calibration("intrinsics", InputsSummary(board="test"),
                            cameras={camera: measured}, station="station1")
