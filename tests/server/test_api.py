"""REST API through the real app (ASGI, same middleware and auth as production): measurements."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import sqlalchemy as sa
from apps import ENGINEER, record_some, settings
from asgi import running
from postgres import PostgresCluster
from records import T0

from mvpose_core.reasons import Reason
from server.app import create_app


@pytest.fixture(params=["sqlite", "postgresql"])
def db(request: pytest.FixtureRequest, tmp_path: Path) -> dict[str, str]:
    """Settings overrides selecting the backend (default SQLite under tmp_path)."""
    if request.param == "sqlite":
        return {}
    cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
    return {"database_url": cluster.create_database()}


OK, MISSING, RMS = Reason.OK, Reason.MARKS_MISSING, Reason.RESIDUAL_RMS_HIGH
REASONS = [OK, OK, MISSING, OK, RMS, OK, OK, MISSING, OK, OK, OK, RMS]


async def test_list_filters_and_cursor_paging(tmp_path: Path, db: dict[str, str]) -> None:
    async with running(create_app(settings(tmp_path, **db)), ENGINEER) as (client, state):
        stored = await record_some(state["services"], REASONS)
        seen, cursor = [], None
        while True:
            params = {"limit": 5} | ({"cursor": cursor} if cursor else {})
            r = await client.get("/api/v1/measurements", params=params)
            assert r.status_code == 200, r.text
            seen += [item["id"] for item in r.json()["items"]]
            cursor = r.json()["next_cursor"]
            if cursor is None:
                break
        assert seen == [m.id for m in reversed(stored)]

        r = await client.get("/api/v1/measurements", params={"result": "NOK"})
        items = r.json()["items"]
        assert {i["trigger_id"] for i in items} == {3, 5, 8, 12}
        assert all(i["offset"] is None and i["result"] == "NOK" for i in items)
        r = await client.get("/api/v1/measurements", params={"reason_code": int(RMS)})
        assert [i["reason"] for i in r.json()["items"]] == ["RESIDUAL_RMS_HIGH"] * 2
        r = await client.get("/api/v1/measurements", params={"part_id": "VIN000004"})
        assert [i["trigger_id"] for i in r.json()["items"]] == [4]
        # triggered_at = T0 + 30 s * trigger_id; the window is [since, until)
        since, until = T0.replace(minute=2).isoformat(), T0.replace(minute=4).isoformat()
        r = await client.get("/api/v1/measurements", params={"since": since, "until": until})
        assert sorted(i["trigger_id"] for i in r.json()["items"]) == [4, 5, 6, 7]
        r = await client.get("/api/v1/measurements", params={"recipe": "nothing"})
        assert r.json() == {"items": [], "next_cursor": None}
        first = r = await client.get("/api/v1/measurements", params={"limit": 1})
        item = first.json()["items"][0]
        assert item["total_ms"] == stored[-1].record.timings_ms["total"]
        assert item["hash"] == stored[-1].hash


async def test_csv_and_json_export(tmp_path: Path, db: dict[str, str]) -> None:
    async with running(create_app(settings(tmp_path, **db)), ENGINEER) as (client, state):
        stored = await record_some(state["services"], REASONS)
        r = await client.get("/api/v1/measurements/export", params={"format": "csv"})
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/csv")
        assert "attachment" in r.headers["content-disposition"]
        rows = list(csv.DictReader(io.StringIO(r.text)))
        assert [int(row["id"]) for row in rows] == [m.id for m in stored]  # oldest first
        for row, m in zip(rows, stored, strict=True):
            assert row["result"] == m.record.result and row["hash"] == m.hash
            if m.record.offset is not None:
                got = [float(row[f"o{k}"]) for k in range(1, 7)]
                np.testing.assert_allclose(got, m.record.offset.values, rtol=0, atol=1e-9)
                assert row["convention"] == "fanuc" and row["o7"] == ""
            else:
                assert row["o1"] == "" and row["sigma_mm"] == ""
            assert json.loads(row["timings_ms"]) == m.record.timings_ms
            # a SHOWN field of the result event has a column of its own
            rms = m.record.residuals.rms_px if m.record.residuals is not None else None
            assert (float(row["residual_rms_px"]) if row["residual_rms_px"] else None) == rms

        r = await client.get("/api/v1/measurements/export",
                             params={"format": "json", "result": "NOK"})
        data = r.json()
        assert [d["hash"] for d in data] == [m.hash for m in stored if m.record.result == "NOK"]
        assert data[0]["record"]["detections"][0]["detections"][0]["reason"] == "low contrast"


async def test_one_measurement_with_detections_and_images(tmp_path: Path) -> None:
    app = create_app(settings(tmp_path, images_quota_mb=1.0))
    async with running(app, ENGINEER) as (client, state):
        services = state["services"]
        cams = [(1, "cam1"), (1, "cam2")]
        refs = services.images.plan(services.station_name, 1, T0, False, cams)
        (m,) = await record_some(services, [MISSING], images=refs)
        frame = np.random.default_rng(1).integers(0, 256, (32, 48), dtype=np.uint8)
        services.images.write(m.id, refs[:1], False, {cams[0]: frame})

        r = await client.get(f"/api/v1/measurements/{m.id}")
        assert r.status_code == 200
        body = r.json()
        assert body["record"]["reason"] == "MARKS_MISSING"
        assert len(body["record"]["detections"]) == 4
        assert [s["state"] for s in body["image_status"]] == ["stored", "pending"]

        r = await client.get(f"/api/v1/measurements/{m.id}/images/1/cam1")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        back = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(back, frame)
        r = await client.get(f"/api/v1/measurements/{m.id}/images/1/cam2")
        assert r.status_code == 404 and "no archived image" in r.json()["detail"]

        rows = services.store.images.for_measurement(m.id)
        services.store.images.mark_evicted([i.id for i in rows])
        r = await client.get(f"/api/v1/measurements/{m.id}/images/1/cam1")
        assert r.status_code == 404 and "evicted" in r.json()["detail"]
        r = await client.get(f"/api/v1/measurements/{m.id}")
        assert r.json()["image_status"][0]["state"] == "evicted"


async def test_chain_endpoint_reports_tampering(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        stored = await record_some(state["services"], REASONS[:5])
        r = await client.get("/api/v1/measurements/chain")
        assert r.json()["ok"] and r.json()["checked"] == 5
        assert r.json()["head_hash"] == stored[-1].hash
        engine = state["services"].store.engine
        with engine.begin() as conn:
            conn.execute(sa.text("DROP TRIGGER measurements_no_update"))
            conn.execute(sa.text("UPDATE measurements SET reason_code = 0 WHERE seq = 3"))
        r = await client.get("/api/v1/measurements/chain")
        assert r.status_code == 200
        assert not r.json()["ok"] and r.json()["first_bad_seq"] == 3
        assert "reason_code" in r.json()["problem"]


async def test_everything_survives_a_restart(tmp_path: Path, db: dict[str, str]) -> None:
    async with running(create_app(settings(tmp_path, **db)), ENGINEER) as (client, state):
        stored = await record_some(state["services"], REASONS[:4])
    async with running(create_app(settings(tmp_path, **db)), ENGINEER) as (client, state):
        more = await record_some(state["services"], REASONS[4:6], seed=1)
        r = await client.get("/api/v1/measurements", params={"limit": 100})
        assert [i["id"] for i in r.json()["items"]] == [m.id for m in reversed(stored + more)]
        r = await client.get("/api/v1/measurements/chain")
        assert r.json()["ok"] and r.json()["checked"] == 6
        r = await client.get("/api/v1/recipes")
        assert r.json()[0]["latest_version"] == 1  # seeding again is a no-op


async def test_metrics_count_results_and_stage_latencies(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        stored = await record_some(state["services"], [OK, OK, MISSING])
        r = await client.get("/api/v1/metrics")
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        text = r.text
        assert 'mvpose_measurements_total{reason="OK",reason_code="0",result="OK"} 2.0' in text
        assert ('mvpose_measurements_total{reason="MARKS_MISSING",reason_code="1",result="NOK"} 1.0'
                in text)
        assert 'mvpose_stage_duration_seconds_count{stage="capture"} 3.0' in text
        total = sum(m.record.timings_ms["detect"] for m in stored) / 1e3
        line = next(x for x in text.splitlines()
                    if x.startswith('mvpose_stage_duration_seconds_sum{stage="detect"}'))
        assert abs(float(line.split()[-1]) - total) < 1e-9
        assert "mvpose_chain_head_seq 3.0" in text
