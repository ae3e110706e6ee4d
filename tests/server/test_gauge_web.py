"""The operator page's Gauge tab through the real app: the list of studies and one study with
its plots and report links; the session cookie also fetches the PDF report."""

from __future__ import annotations

from pathlib import Path

import anyio.to_thread
import numpy as np
from apps import ENGINEER, settings
from asgi import running
from gauge_data import TRUE, store_repeats

from server.app import create_app
from server.state import Services

ORIGIN = {"Origin": "http://station"}


async def test_the_gauge_tab_lists_studies_and_shows_one_with_its_plots(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path))) as (client, state):
        r = await client.get("/gauge", follow_redirects=False)
        assert r.status_code in (302, 303, 307)  # log in first
        r = await client.post("/web/login", json={"token": ENGINEER}, headers=ORIGIN)
        assert r.status_code == 200, r.text
        r = await client.get("/gauge")
        assert r.status_code == 200 and "No gauge study stored yet" in r.text
        assert 'href="/gauge" class="on"' in r.text

        services: Services = state["services"]
        rng = np.random.default_rng(4)
        await anyio.to_thread.run_sync(store_repeats, services.store, rng, "VIN-M", 25)
        r = await client.post("/api/v1/gauge/studies", headers=ORIGIN, json={
            "kind": "type1", "part_id": "VIN-M", "reference": list(TRUE), "title": "master"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]

        r = await client.get("/gauge")
        assert f"href='/gauge/{sid}'" in r.text and "master" in r.text and "passed" in r.text
        r = await client.get(f"/gauge/{sid}")
        assert r.status_code == 200
        assert r.text.count("<svg") == 10 and "PASSED" in r.text
        assert f"/api/v1/gauge/studies/{sid}/report.pdf" in r.text
        r = await client.get(f"/api/v1/gauge/studies/{sid}/report.pdf")
        assert r.status_code == 200 and r.content.startswith(b"%PDF")
        r = await client.get("/gauge/77")
        assert r.status_code == 404 and "gauge study 77 does not exist" in r.text
