"""Drift watch and reference check over the real store and app: records in, report and verdict out.

The records carry per-camera residual means as the pipeline stores them; their drift-free part
is N(0, σ²) and a moved camera adds what the real estimator's response on station 1 predicts
(mvpose_core.residuals.shift_response), so the service's camera attribution is exercised too.
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from apps import ENGINEER, STATION1, settings
from asgi import running
from records import T0, make_record

from mvpose_core.drift import DriftOptions
from mvpose_core.measure import measure
from mvpose_core.reasons import Reason
from mvpose_core.residuals import shift_response
from mvpose_core.station import DriftConfig, load_station
from mvpose_core.synth import synthetic_observations
from mvpose_core.transforms import xyzwpr_to_matrix
from server.app import create_app
from server.drift import DriftService, record_camera_residuals
from server.store import Store, open_store
from server.store.schemas import MeasurementRecord

SIGMA_PX = 0.04


def _record(rng: np.random.Generator, i: int, cams: list[tuple[int, str]] | None,
            extra: dict[tuple[int, str], np.ndarray] | None = None, **kw: Any) -> MeasurementRecord:
    rec = make_record(rng, trigger_id=i, triggered_at=T0 + timedelta(seconds=30 * i), **kw)
    data = rec.model_dump()
    if cams is not None:
        data["camera_residuals"] = [
            {"view": v, "camera_id": c, "count": 2, "used": 2, "rms_px": 0.1,
             "mean_px": tuple(float(x) for x in rng.normal(0.0, SIGMA_PX, 2)
                              + (extra or {}).get((v, c), 0.0))}
            for v, c in cams
        ]
    return MeasurementRecord.model_validate(data)


@pytest.fixture
def store(tmp_path: Path) -> Any:
    s = open_store(f"sqlite:///{tmp_path / 'drift.sqlite'}", "station1", "NORMAL")
    yield s
    s.close()


def test_service_learns_flags_the_moved_camera_and_reads_only_new_records(store: Store) -> None:
    station = load_station(STATION1)
    response = shift_response(station, station.recipes[0])
    cams = sorted(response)
    rng = np.random.default_rng(3)
    old = [store.measurements.insert(_record(rng, i, None)) for i in range(1, 11)]
    service = DriftService(store, station)
    first = service.report()
    assert (first.status, first.records, first.cameras) == ("learning", 0, [])
    assert first.last_id == old[-1].id  # records before the drift watch are read and skipped

    warm = DriftOptions().warmup
    for i in range(11, 11 + warm + 20):
        store.measurements.insert(_record(rng, i, cams))
    calm = service.report()
    assert calm.status == "ok" and calm.records == warm + 20 and calm.messages == []
    assert [(c.view, c.camera_id) for c in calm.cameras] == cams
    for c in calm.cameras:
        assert c.status == "ok" and c.learning_left == 0 and c.triggers == 20
        assert c.baseline_sigma_px == pytest.approx((SIGMA_PX, SIGMA_PX), rel=0.15)
        assert len(c.trend) == 500 and c.trend[-1].id == calm.last_id
    assert calm.rule.arl0_alarm > 5e7 and calm.calibration_id == "cal-2026-11-01"

    moved, move = (1, "top_right"), np.array([0.0, 1.0])
    extra = {seen: response[moved][seen] @ move for seen in cams}
    shifted = [store.measurements.insert(_record(rng, i, cams, extra))
               for i in range(11 + warm + 20, 11 + warm + 60)]
    report = service.report()
    assert report.status == "alarm" and report.last_id == shifted[-1].id
    flagged = {c.camera_id: c for c in report.cameras if c.status == "alarm"}
    assert "top_right" in flagged
    c = flagged["top_right"]
    assert (c.moved_view, c.moved_camera) == moved
    assert c.shift_px == pytest.approx(1.0, abs=0.25)
    assert c.since_id is not None and abs(c.since_id - shifted[0].id) <= 2
    assert c.since == store.measurements.get(c.since_id).record.triggered_at
    assert c.message.startswith(f"camera top_right moved ~{c.shift_px:.1f} px since ")
    assert c.message in report.messages
    assert store.measurements.verify_chain().ok  # old and new records side by side


def test_record_camera_residuals_come_from_the_measurement() -> None:
    station = load_station(STATION1)
    recipe = station.recipes[0]
    obs = synthetic_observations(station, recipe, recipe.T_rf_from_pf0.matrix,
                                 np.random.default_rng(4), 0.1)
    meas = measure(station, recipe, obs)
    rows = record_camera_residuals(obs, meas)
    assert [(r.view, r.camera_id, r.count, r.used) for r in rows] == [
        (1, "back_left", 2, 2), (1, "back_right", 2, 2), (1, "top_left", 2, 2),
        (1, "top_right", 2, 2)]
    r = meas.pose.residuals_px
    assert rows[0].mean_px == pytest.approx(tuple(r[[o.camera_id == "back_left" for o in obs]]
                                                  .mean(axis=0)), abs=1e-6)


async def _tokens(client: Any) -> dict[str, str]:
    out = {}
    for role in ("read", "operator"):
        r = await client.post("/api/v1/tokens", json={"name": f"drift-{role}", "role": role})
        assert r.status_code == 201, r.text
        out[role] = r.json()["token"]
    return out


async def test_drift_endpoint_and_verify_by_role(tmp_path: Path) -> None:
    async with running(create_app(settings(tmp_path)), ENGINEER) as (client, state):
        tokens = await _tokens(client)
        read = {"Authorization": f"Bearer {tokens['read']}"}
        op = {"Authorization": f"Bearer {tokens['operator']}"}
        store = state["services"].store
        recipe = load_station(STATION1).recipes[0]
        rng = np.random.default_rng(5)
        T_ref = recipe.T_rf_from_pf0.matrix
        cams = [(1, "top_left"), (1, "top_right")]
        at_ref = _record(rng, 1, cams).model_copy(
            update={"T_rf_from_pf": MeasurementRecord.matrix(T_ref)})
        off = T_ref @ xyzwpr_to_matrix([1.5, 0.0, 0.0, 0.0, 0.0, 0.0])  # 1.5 mm along PF x
        moved = _record(rng, 2, cams).model_copy(
            update={"T_rf_from_pf": MeasurementRecord.matrix(off)})
        nok = _record(rng, 3, cams, reason=Reason.MARKS_MISSING)
        ids = [store.measurements.insert(r).id for r in (at_ref, moved, nok)]

        r = await client.get("/api/v1/drift", headers=read)
        assert r.status_code == 200, r.text
        body = r.json()
        assert body["status"] == "learning" and body["records"] == 3
        assert [c["camera_id"] for c in body["cameras"]] == ["top_left", "top_right"]
        assert body["cameras"][0]["learning_left"] == DriftOptions().warmup - 3
        assert len(body["cameras"][0]["trend"]) == 3

        url = "/api/v1/calibration/verify"
        r = await client.post(url, json={"measurement_id": ids[0]}, headers=read)
        assert r.status_code == 403, r.text
        r = await client.post(url, json={"measurement_id": ids[0]}, headers=op)
        assert r.status_code == 200, r.text
        good = r.json()
        assert good["passed"] is True
        assert good["grasp_displacement_mm"] == pytest.approx(0, abs=1e-9)
        assert good["limit_mm"] == recipe.tolerances.translation_mm
        assert good["message"].endswith(": pass")
        r = await client.post(url, json={"measurement_id": ids[1]}, headers=op)
        bad = r.json()
        assert bad["passed"] is False
        assert bad["grasp_displacement_mm"] == pytest.approx(1.5, abs=1e-6)
        assert bad["margin_mm"] == pytest.approx(recipe.tolerances.translation_mm - 1.5, abs=1e-6)
        assert bad["message"].endswith("FAIL by 0.500 mm")
        r = await client.post(url, json={"measurement_id": ids[2]}, headers=op)
        assert r.status_code == 409 and "MARKS_MISSING" in r.json()["detail"]
        r = await client.post(url, json={"measurement_id": 10**6}, headers=op)
        assert r.status_code == 404
        for value in (True, "1", 0, 2**63):
            r = await client.post(url, json={"measurement_id": value}, headers=op)
            assert r.status_code == 422, (value, r.text)

        # the drift watch links to the newest verify (a record with part id VERIFY), judged
        assert body["last_verify"] is None
        verify = store.measurements.insert(moved.model_copy(
            update={"part_id": "VERIFY", "trigger_id": 0}))
        last = (await client.get("/api/v1/drift", headers=read)).json()["last_verify"]
        assert (last["measurement_id"], last["result_id"], last["passed"]) == (
            verify.id, verify.seq, False)
        assert last["message"].endswith("FAIL by 0.500 mm")
        # a verify that measures needs the station: this app has none
        r = await client.post(url, headers=op)
        assert r.status_code == 503, r.text

        spec = (await client.get("/openapi.json")).json()
        drift = spec["paths"]["/api/v1/drift"]["get"]
        assert drift["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith(
            "/DriftReport")
        assert "CameraDriftReport" in spec["components"]["schemas"]
        assert {"404", "409"} <= set(spec["paths"][url]["post"]["responses"])


def test_service_keeps_the_station_files_history_and_dates_only_within_it(store: Store) -> None:
    station = load_station(STATION1).model_copy(update={"drift": DriftConfig(history=100)})
    response = shift_response(station, station.recipes[0])
    cams = sorted(response)
    service = DriftService(store, station)
    assert service.options.history == 100
    rng = np.random.default_rng(5)
    n = 1 + DriftOptions().warmup + 20
    for i in range(1, n):
        store.measurements.insert(_record(rng, i, cams))
    assert service.report().status == "ok"
    moved = (1, "top_right")
    extra = {seen: response[moved][seen] @ np.array([0.0, 1.0]) for seen in cams}
    shifted = [store.measurements.insert(_record(rng, i, cams, extra)) for i in range(n, n + 40)]
    c = next(c for c in service.report().cameras if c.camera_id == "top_right")
    assert c.status == "alarm" and c.since_id is not None
    assert abs(c.since_id - shifted[0].id) <= 2
    assert c.since == store.measurements.get(c.since_id).record.triggered_at
    for i in range(n + 40, n + 140):  # the change point falls out of the last 100 triggers
        store.measurements.insert(_record(rng, i, cams, extra))
    c = next(c for c in service.report().cameras if c.camera_id == "top_right")
    assert c.status == "alarm" and (c.since_id, c.since) == (None, None)
    assert c.shift_px == pytest.approx(1.0, abs=0.25)  # measured over the kept triggers
    assert c.message.startswith("camera top_right moved ~") and "since" not in c.message


def test_the_watch_reads_only_residuals_above_the_last_id_newest_window_oldest_first(
        store: Store) -> None:
    station = load_station(STATION1)
    cams = sorted(shift_response(station, station.recipes[0]))
    rng = np.random.default_rng(6)
    stored = [store.measurements.insert(_record(rng, i, cams if i % 3 else None))
              for i in range(1, 13)]
    got = store.measurements.residuals_after(stored[3].id, 5)
    assert [r.id for r in got] == [s.id for s in stored[-5:]]  # the newest 5, oldest first
    for r, s in zip(got, stored[-5:], strict=True):
        assert (r.recipe, r.triggered_at, r.calibration_id, r.calibration_hash) == (
            s.record.recipe, s.record.triggered_at, s.record.calibration_id,
            s.record.calibration_hash)
        assert r.camera_residuals == (s.record.camera_residuals or [])
    assert [r.id for r in store.measurements.residuals_after(stored[9].id, 5)] == [
        stored[10].id, stored[11].id]
    assert store.measurements.residuals_after(stored[-1].id, 5) == []


def _learn_then_move(store: Store, station: Any, seed: int, moved: tuple[int, str],
                     move: tuple[float, float]) -> None:
    """Records through the learning window and 20 more, then 40 with camera ``moved`` shifted
    by ``move`` px (as the estimator's response shows it in every camera)."""
    response = shift_response(station, station.recipes[0])
    cams = sorted(response)
    rng = np.random.default_rng(seed)
    n = 1 + DriftOptions().warmup + 20
    extra = {seen: response[moved][seen] @ np.array(move) for seen in cams}
    for i in range(1, n + 40):
        store.measurements.insert(_record(rng, i, cams, extra if i >= n else None))


def test_the_alarm_watchs_states_are_the_reports_without_the_trend(store: Store) -> None:
    station = load_station(STATION1)
    _learn_then_move(store, station, 7, (1, "top_right"), (0.0, 1.0))
    full, light = DriftService(store, station).report(), DriftService(store, station).cameras()
    assert full.status == "alarm" and all(len(c.trend) > 0 for c in full.cameras)
    assert light == [c.model_copy(update={"trend": []}) for c in full.cameras]


def test_the_alarm_watch_hears_nothing_before_any_record(tmp_path: Path) -> None:
    empty = open_store(f"sqlite:///{tmp_path / 'empty.sqlite'}", "station1", "NORMAL")
    try:
        assert DriftService(empty, load_station(STATION1)).cameras() == []
    finally:
        empty.close()


def test_a_prepared_response_attributes_the_move_and_an_unknown_recipe_prepares_none(
        store: Store) -> None:
    station = load_station(STATION1)
    service = DriftService(store, station)
    service.prepare(station.recipes[0].name)
    service.prepare("no-such-recipe")  # nothing to attribute with, and no error
    moved = (1, "back_left")
    _learn_then_move(store, station, 8, moved, (1.0, 0.0))
    flagged = [c for c in service.cameras() if c.status == "alarm"]
    assert flagged and {(c.moved_view, c.moved_camera) for c in flagged} == {moved}
