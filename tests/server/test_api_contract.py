"""What the API promises besides its happy paths: bounded integers, the OpenAPI's statuses, 405."""

from __future__ import annotations

from pathlib import Path

from apps import ENGINEER, settings
from asgi import running

from server.app import create_app

PROBLEM = "application/problem+json"
BIG = 2**63  # one past BIGINT

BODIES = [  # (url, body, field): every integer of every body is bounded and no boolean
    ("/api/v1/station/teach", {"measurement_id": BIG}, "measurement_id"),
    ("/api/v1/station/teach", {"measurement_id": 10**30}, "measurement_id"),
    ("/api/v1/station/teach", {"measurement_id": True}, "measurement_id"),
    ("/api/v1/station/teach", {"measurement_id": "7"}, "measurement_id"),
    ("/api/v1/station/teach", {"measurement_id": 7.5}, "measurement_id"),
    ("/api/v1/station/teach", {"measurement_id": 0}, "measurement_id"),
    ("/api/v1/station/recipe", {"name": "floor_panel", "version": BIG}, "version"),
    ("/api/v1/station/recipe", {"name": "floor_panel", "version": 2**31}, "version"),
    ("/api/v1/station/recipe", {"name": "floor_panel", "version": False}, "version"),
    ("/api/v1/station/trigger", {"view": True}, "view"),
    ("/api/v1/station/trigger", {"view": 256}, "view"),
    ("/api/v1/station/trigger", {"trigger_id": 2**32}, "trigger_id"),
    ("/api/v1/station/trigger", {"trigger_id": -1}, "trigger_id"),
    ("/api/v1/calibrations/c/versions", {"content": {"x": 1}, "activate": 1}, "activate"),
    ("/api/v1/calibrations/c/versions", {"content": {"x": 1}, "activate": "yes"}, "activate"),
]


async def test_out_of_range_or_boolean_integers_are_a_422_naming_the_field(
    tmp_path: Path
) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, _):
        for url, body, field in BODIES:
            r = await client.post(url, json=body)
            assert r.status_code == 422, (url, body, r.text)
            assert r.headers["content-type"] == PROBLEM
            assert f"body.{field}:" in r.json()["detail"], (url, body)
            assert [e["loc"] for e in r.json()["errors"]][0][:2] == ["body", field]


async def test_integral_json_numbers_are_integers(tmp_path: Path) -> None:
    # JSON Schema's "integer" (what the OpenAPI says) takes 7.0; the request then reaches the
    # station, which is not running here: 503, not 422.
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, _):
        for url, body in [("/api/v1/station/teach", {"measurement_id": 7.0}),
                          ("/api/v1/station/teach", {"measurement_id": 2**63 - 1}),
                          ("/api/v1/station/recipe", {"name": "floor_panel", "version": 2.0}),
                          ("/api/v1/station/trigger", {"view": 255, "trigger_id": 2**32 - 1})]:
            r = await client.post(url, json=body)
            assert r.status_code == 503, (url, body, r.text)


QUERIES = [
    ("/api/v1/measurements?limit=true", "limit"),
    ("/api/v1/measurements?limit=1001", "limit"),
    ("/api/v1/measurements?reason_code=65536", "reason_code"),
    ("/api/v1/measurements?reason_code=true", "reason_code"),
    (f"/api/v1/measurements?result_id={BIG}", "result_id"),
    ("/api/v1/measurements?until=0.5", "until"),  # not a Unix time either
    ("/api/v1/measurements/export?since=1700000000", "since"),
    (f"/api/v1/measurements/{BIG}", "measurement_id"),
    (f"/api/v1/measurements/1/images/{BIG}/cam1", "view"),
    (f"/api/v1/recipes/floor_panel/versions/{2**31}", "version"),
    (f"/api/v1/calibrations/c/versions/{BIG}/activate", "version"),
]


async def test_out_of_range_query_and_path_integers_are_a_422(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, _):
        for url, field in QUERIES:
            method = "POST" if url.endswith("/activate") else "GET"
            r = await client.request(method, url)
            assert r.status_code == 422, (url, r.text)
            assert f".{field}:" in r.json()["detail"], url


async def test_openapi_declares_every_status_as_a_problem(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, _):
        spec = (await client.get("/openapi.json")).json()
    ops = {f"{m.upper()} {p}": op for p, item in spec["paths"].items() for m, op in item.items()}
    for name, op in ops.items():
        for status, response in op["responses"].items():
            if int(status) >= 400:  # problems only as problem+json, with its schema
                assert list(response["content"]) == [PROBLEM], (name, status)
        assert {"400", "413"} <= set(op["responses"]), name  # the body limit sees every request
    assert "HTTPValidationError" not in spec["components"]["schemas"]
    assert set(spec["components"]["schemas"]["Problem"]["required"]) == {
        "type", "title", "status", "detail"}

    def statuses(name: str) -> set[str]:
        return {s for s in ops[name]["responses"] if int(s) >= 400}

    auth = {"400", "401", "403", "413", "503"}
    assert statuses("GET /api/v1/measurements") == auth | {"422"}
    assert statuses("GET /api/v1/measurements/{measurement_id}") == auth | {"404", "422"}
    assert statuses("POST /api/v1/tokens") == auth | {"409", "422"}
    assert statuses("DELETE /api/v1/tokens/{name}") == auth | {"404", "409", "422"}
    assert statuses("POST /api/v1/station/teach") == auth | {"404", "409", "422"}
    assert statuses("GET /api/v1/health/live") == {"400", "413"}
    assert statuses("GET /api/v1/health/ready") == {"400", "413", "503"}
    body = spec["components"]["schemas"]["TeachBody"]["properties"]["measurement_id"]
    assert body["anyOf"][0] == {"type": "integer", "minimum": 1, "maximum": 2**63 - 1}


async def test_405_names_every_method_of_the_path(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, _):
        for method, url, allow in [
            ("PUT", "/api/v1/tokens", "GET, POST"),
            ("OPTIONS", "/api/v1/recipes/floor_panel/versions", "GET, POST"),
            ("PATCH", "/api/v1/tokens/mes", "DELETE"),
            ("DELETE", "/api/v1/measurements", "GET"),
        ]:
            r = await client.request(method, url)
            assert r.status_code == 405, (method, url)
            assert r.headers["allow"] == allow, (method, url)
            assert r.headers["content-type"] == PROBLEM
