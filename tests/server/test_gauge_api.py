"""REST /api/v1/gauge/studies through the real app: run a study on stored measurements, list,
fetch, download its reports; bad requests are named 422s, never 500s."""

from __future__ import annotations

from pathlib import Path

import anyio.to_thread
import numpy as np
from apps import ENGINEER, settings
from asgi import running
from gauge_data import TRUE, store_repeats

from server.app import create_app
from server.auth import hash_secret
from server.state import Services

READER = "mvp_reader-secret-for-the-gauge-tests-000000"


async def test_a_type1_study_is_run_stored_listed_and_reported(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        services: Services = state["services"]
        rng = np.random.default_rng(2)
        seqs = await anyio.to_thread.run_sync(store_repeats, services.store, rng, "VIN-M", 26)
        r = await client.post("/api/v1/gauge/studies", json={
            "kind": "type1", "part_id": "VIN-M", "reference": list(TRUE),
            "title": "master part"})
        assert r.status_code == 201, r.text
        study = r.json()
        assert study["passed"] is True and study["seq"] == 1 and study["created_by"]
        assert [f["name"] for f in study["figures"]][-1] == "grasp |dT|"
        assert {rec["seq"] for rec in study["records"]} == set(seqs)
        x = study["figures"][0]
        assert x["cg"] >= 1.33 and x["cgk"] >= 1.33 and x["n"] == 26

        r = await client.get("/api/v1/gauge/studies")
        assert [s["id"] for s in r.json()] == [study["id"]]
        assert r.json()[0]["title"] == "master part"
        r = await client.get(f"/api/v1/gauge/studies/{study['id']}")
        assert r.json()["hash"] == study["hash"]
        r = await client.get(f"/api/v1/gauge/studies/{study['id']}/report.html")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert study["hash"] in r.text and "<svg" in r.text
        r = await client.get(f"/api/v1/gauge/studies/{study['id']}/report.pdf")
        assert r.status_code == 200 and r.content.startswith(b"%PDF")

        r = await client.get("/api/v1/gauge/studies/99")
        assert r.status_code == 404 and "gauge study 99" in r.json()["detail"]


async def test_bad_studies_are_named(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        services: Services = state["services"]
        rng = np.random.default_rng(3)
        await anyio.to_thread.run_sync(store_repeats, services.store, rng, "VIN-M", 10)
        r = await client.post("/api/v1/gauge/studies", json={"kind": "type1",
                                                            "part_id": "VIN-M"})
        assert r.status_code == 400 and "at least 25 measurements" in r.json()["detail"]
        r = await client.post("/api/v1/gauge/studies", json={"kind": "type3"})
        assert r.status_code == 400 and "2 or more parts" in r.json()["detail"]
        r = await client.post("/api/v1/gauge/studies", json={"kind": "type1", "part_id": "nope"})
        assert r.status_code == 400 and "no OK measurement" in r.json()["detail"]
        r = await client.post("/api/v1/gauge/studies", json={"kind": "type9"})
        assert r.status_code == 422
        r = await client.post("/api/v1/gauge/studies", json={"kind": "linearity"})
        assert r.status_code == 400 and "known displacements" in r.json()["detail"]
        r = await client.post("/api/v1/gauge/studies",
                              json={"kind": "type1", "recipe": "no_such_recipe"})
        assert r.status_code == 404


async def test_running_a_study_needs_the_engineer(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), READER) as (client, state):
        services: Services = state["services"]
        await anyio.to_thread.run_sync(services.store.tokens.create, "reader", "read",
                                       hash_secret(READER))
        r = await client.post("/api/v1/gauge/studies", json={"kind": "type1"})
        assert r.status_code == 403, r.text
        r = await client.get("/api/v1/gauge/studies")
        assert r.status_code == 200 and r.json() == []
