"""End to end on loopback: the PLC twin measures simulated parts; REST, chain, restart, PostgreSQL.

The acceptance run of the station: the twin moves the part to a random known displacement (the
simulated cameras render it before the trigger, as a real part arrives before it is measured),
triggers over Modbus/TCP, and reads the result block; then MES reads everything back over HTTP.
"""

from __future__ import annotations

import asyncio
import csv
import io
import os
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from stations import (
    ENGINEER,
    no_read_noise,
    relaxed_deadline,
    runtime_options,
    settings_for,
    station_file,
)

from drivers.links.codecs import int_scales
from drivers.links.layout import Status
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import to_robot
from server.cli import main as cli_main
from server.loopback import TriggerRow, move_part, running_server, running_station, trigger
from server.settings import Settings

# Rendering four 4 MP frames per part move is what these tests cost: without the cameras' read
# noise (no_read_noise) ~0.1 s of CPU, with it ~0.3 s; the answers are judged against the
# recipe's tolerances, which the detector's noise is far inside. The SQLite run makes the
# acceptance's 200 triggers; the PostgreSQL run checks the same on the other store with 80 (more
# than one page of 70 records, so the paging, the chain and the export cross a page boundary
# too; MVPOSE_E2E_TRIGGERS_PG=200 for the full series). MVPOSE_E2E_TRIGGERS(_PG) shorten them
# for a quick local run.
N_TRIGGERS = int(os.environ.get("MVPOSE_E2E_TRIGGERS", "200"))
N_TRIGGERS_PG = int(os.environ.get("MVPOSE_E2E_TRIGGERS_PG", "80"))


async def _measure_series(
    lb: Any, n: int, seed: int, first_id: int
) -> tuple[list[TriggerRow], dict[int, np.ndarray]]:
    recipe = lb.runtime.active.config
    rng = np.random.default_rng(seed)
    rows, truth = [], {}
    for i in range(n):
        T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, 20.0, 2.0)
        await move_part(lb.runtime, lb.twin, T)
        tid = first_id + i
        status, row = await trigger(lb.twin, recipe, tid, T, part_id=f"BODY-{tid}")
        assert row is not None and status.has(Status.RESULT_VALID)
        rows.append(row)
        truth[tid] = row.true_offset
    return rows, truth


async def _all_measurements(api: httpx.AsyncClient) -> list[dict[str, Any]]:
    items, cursor = [], None
    while True:
        params: dict[str, Any] = {"limit": 70}
        if cursor:
            params["cursor"] = cursor
        page = (await api.get("/measurements", params=params)).json()
        items += page["items"]
        cursor = page["next_cursor"]
        if not cursor:
            return items


def _check_series(rows: list[TriggerRow], recipe: Any) -> None:
    codes = [r.result_code for r in rows]
    nok = [(r.trigger_id, r.result_code) for r in rows if r.result_code]
    assert codes == [0] * len(rows), f"NOK results: {nok}"
    tol = recipe.tolerances
    worst_deg = max(r.rot_err_deg for r in rows)
    worst_mm = max(r.trans_err_mm for r in rows)
    assert worst_deg <= tol.rotation_deg and worst_mm <= tol.translation_mm, (worst_deg, worst_mm)
    # The reported 1σ is what the gate judged: within the tolerances too.
    assert max(r.sigma_mm for r in rows) <= tol.translation_mm


async def _run_and_restart(tmp_path: Path, settings: Settings, n: int, seed: int) -> None:
    recipe_name = "floor_panel"
    async with running_station(settings, runtime_options(seed)) as lb:
        recipe = lb.runtime.active.config
        assert recipe.name == recipe_name
        rows, truth = await _measure_series(lb, n, seed, first_id=1)
        _check_series(rows, recipe)
        lb.runtime.wait_idle()
        async with httpx.AsyncClient(base_url=lb.base_url + "/api/v1", timeout=30,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            items = await _all_measurements(api)
            ids = sorted(m["trigger_id"] for m in items)
            assert ids == list(range(1, n + 1)), "every trigger stored exactly once"
            by_id = {m["trigger_id"]: m for m in items}
            for r in rows:
                stored = np.array(by_id[r.trigger_id]["offset"]["values"])
                # The PLC reads float32; the record holds the double it was made from.
                np.testing.assert_allclose(r.measured_offset, stored, atol=1e-3)
                assert by_id[r.trigger_id]["part_id"] == f"BODY-{r.trigger_id}"
            chain = (await api.get("/measurements/chain")).json()
            assert chain["ok"] and chain["checked"] == n, chain
            export = (await api.get("/measurements/export", params={"format": "csv"})).text
    # Commissioning validation on the MES export against the simulator's truth.
    truth_csv = tmp_path / "truth.csv"
    with truth_csv.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["trigger_id", *recipe.robot_convention.labels])
        w.writerows([tid, *(f"{v:.6f}" for v in off)] for tid, off in truth.items())
    (tmp_path / "export.csv").write_text(export)
    assert len(list(csv.DictReader(io.StringIO(export)))) == n
    assert cli_main(["validate", "--station", str(settings.station), "--truth", str(truth_csv),
                     "--measured", str(tmp_path / "export.csv")]) == 0

    # Restart: the same store, nothing lost, the chain continues.
    async with running_station(settings, runtime_options(seed + 1)) as lb:
        rows2, _ = await _measure_series(lb, 1, seed + 1, first_id=n + 1)
        _check_series(rows2, recipe)
        lb.runtime.wait_idle()
        async with httpx.AsyncClient(base_url=lb.base_url + "/api/v1", timeout=30,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            items = await _all_measurements(api)
            assert sorted(m["trigger_id"] for m in items) == list(range(1, n + 2))
            chain = (await api.get("/measurements/chain")).json()
            assert chain["ok"] and chain["checked"] == n + 1, chain


@pytest.mark.timeout(600)
async def test_station1_sqlite_every_trigger_stored_once_within_tolerance(tmp_path: Path) -> None:
    station = station_file(tmp_path, "station1", relaxed_deadline, no_read_noise)
    settings = settings_for(station, tmp_path / "var")
    await _run_and_restart(tmp_path, settings, N_TRIGGERS, seed=11)


@pytest.mark.timeout(600)
async def test_station1_postgresql(tmp_path: Path, postgres_cluster: Any) -> None:
    url = postgres_cluster.create_database()
    station = station_file(tmp_path, "station1", relaxed_deadline, no_read_noise)
    settings = settings_for(station, tmp_path / "var", url)
    await _run_and_restart(tmp_path, settings, N_TRIGGERS_PG, seed=23)


@pytest.mark.timeout(300)
async def test_lab_robot_mounted_two_views_through_the_plc(tmp_path: Path) -> None:
    """Paper Section 3.2: the stereo pair on the flange, a trigger per view, the estimate after
    the last; the robot reports its actual flange pose, which is off the taught one."""
    settings = settings_for(station_file(tmp_path, "lab", relaxed_deadline), tmp_path / "var")
    rng = np.random.default_rng(5)
    async with running_station(settings, runtime_options(5)) as lb:
        rt = lb.runtime
        recipe = rt.active.config
        conv = recipe.robot_convention
        scales = int_scales(conv)
        views = [v.id for v in rt.station.views]
        assert views == [1, 2]
        for part in range(4):
            T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, 20.0, 2.0)
            await move_part(rt, lb.twin, T)
            tid = 100 + part
            for view in views:
                taught = rt.station.view(view).T_rf_from_gf.matrix
                # The robot stops 2 mm / 0.2° away from the taught view pose, and says so.
                actual = taught @ random_displacement(rng, 2.0, 0.2)
                rt.scene.set_view(view, actual)
                counts = [round(v * s) for v, s in zip(to_robot(actual, conv), scales, strict=True)]
                # past the watchdog's TIMEOUT and the link's backstop (3 s with the relaxed
                # deadline): the twin's 2 s default took a preempted trigger for a lost one
                status = await lb.twin.cycle(tid, view, pose_counts=counts,
                                             part_id=f"FLOOR-{part}", timeout=5.0)
                if view != views[-1]:
                    assert status.has(Status.VIEW_DONE) and not status.has(Status.RESULT_VALID)
                    assert status.views_done == 1
                else:
                    assert status.has(Status.RESULT_VALID) and status.result_code == 0, (
                        status.result_code, rt.last)
                    _, row = await trigger_row(recipe, T, status)
                    assert row.rot_err_deg <= recipe.tolerances.rotation_deg
                    assert row.trans_err_mm <= recipe.tolerances.translation_mm
        rt.wait_idle()
        rec = rt.services.store.measurements.get(rt.last["measurement_id"]).record
        assert {c.view for c in rec.detections} == {1, 2}
        assert rt.services.store.measurements.count() == 4


async def trigger_row(recipe: Any, T: np.ndarray, status: Any) -> tuple[Any, TriggerRow]:
    """The row for an answer already read (the last view's), compared with the truth."""
    from server.loopback import offset_error, true_offset

    want = true_offset(recipe, T)
    got = np.array(status.offset_float)
    deg, mm = offset_error(recipe, want, got)
    return status, TriggerRow(status.trigger_id, status.result_code, want, got, deg, mm,
                              0.0, 0.0, status.processing_ms, 0.0)


def test_malformed_station_file_stops_startup_naming_file_field_value(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def bad(d: dict[str, Any]) -> None:
        d["cameras"][1]["intrinsics"]["fx"] = -2909.1

    path = station_file(tmp_path, "station1", bad)
    rc = cli_main(["serve", "--station", str(path), "--port", "0", "--plc-port", "0",
                   "--data-dir", str(tmp_path / "var")])
    err = capsys.readouterr().err
    assert rc == 2
    assert str(path) in err and "cameras[1](top_right).intrinsics.fx" in err and "-2909.1" in err
    assert not (tmp_path / "var").exists(), "nothing opened before the station file was valid"


def test_bad_link_options_stop_startup_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    path = station_file(tmp_path, "station1")
    base = ["serve", "--station", str(path), "--port", "0", "--plc-port", "0",
            "--data-dir", str(tmp_path / "var")]
    assert cli_main([*base, "--plc-word-order", "BADC"]) == 2
    err = capsys.readouterr().err
    assert "--plc-word-order" in err and "'BADC'" in err
    monkeypatch.setenv("MVPOSE_PLC_ALLOWLIST", "10.1.2.0/24, plc-7")
    assert cli_main(base) == 2
    err = capsys.readouterr().err
    assert "MVPOSE_PLC_ALLOWLIST" in err and "'plc-7' is not an address" in err
    monkeypatch.delenv("MVPOSE_PLC_ALLOWLIST")
    assert cli_main([*base, "--plc-watchdog-s", "-1"]) == 2
    assert "--plc-watchdog-s" in capsys.readouterr().err
    for cmd in ("station", "api"):  # each process alone checks the same way
        args = [cmd, "--station", str(path), "--data-dir", str(tmp_path / "var")]
        monkeypatch.setenv("MVPOSE_PLC_UNIT_ID", "300")
        assert cli_main(args) == 2
        assert "MVPOSE_PLC_UNIT_ID" in capsys.readouterr().err
    assert not (tmp_path / "var").exists(), "nothing opened before the options were valid"


@pytest.mark.timeout(300)
async def test_lab_two_views_each_trigger_shows_the_view_it_names(tmp_path: Path) -> None:
    """Nothing but the triggers says which view is measured (no test reaches into the scene):
    view 2's capture must show view 2, or its marks are found in view 1's frames."""
    from server.loopback import offset_error, true_offset
    from server.station.client import StationClient

    settings = settings_for(station_file(tmp_path, "lab", relaxed_deadline), tmp_path / "var")
    rng = np.random.default_rng(11)
    async with running_server(settings, runtime_options(11), http_port=None) as srv:
        rt = srv.runtime
        recipe = rt.active.config
        client = StationClient(settings.resolved_control_socket, timeout_s=30.0)
        for part in range(2):
            T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, 20.0, 2.0)
            await move_part(rt, None, T)  # type: ignore[arg-type]
            first = await asyncio.to_thread(client.trigger, f"P{part}", 1)
            assert not first.final and first.views_done == 1, first
            last = await asyncio.to_thread(client.trigger, f"P{part}", 2)
            assert last.final and last.result_code == 0, (last.result_code, last.message)
            deg, mm = offset_error(recipe, true_offset(recipe, T), np.array(last.offset))
            assert deg <= recipe.tolerances.rotation_deg
            assert mm <= recipe.tolerances.translation_mm


@pytest.mark.timeout(300)
async def test_a_rehearsal_moves_only_a_simulated_part(tmp_path: Path) -> None:
    from server.errors import ConflictError
    from server.station.client import StationClient

    # a folder with an image, so the cameras come up at once (the start waits up to 10 s for
    # cameras that are down); nothing is grabbed from it
    folder = tmp_path / "images"
    folder.mkdir()
    (folder / "0001.pgm").write_bytes(b"P5 1 1 255\n\x00")

    def files_cameras(data: dict[str, Any]) -> None:
        for cam in data["cameras"]:
            cam["driver"] = {"kind": "files", "folder": str(folder)}

    path = station_file(tmp_path, "lab", relaxed_deadline, files_cameras)
    settings = settings_for(path, tmp_path / "var")
    async with running_server(settings, runtime_options(), http_port=None):
        client = StationClient(settings.resolved_control_socket)
        with pytest.raises(ConflictError, match="not simulated"):
            await asyncio.to_thread(client.move_part, [0.0] * 6)
