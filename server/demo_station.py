"""The server demo of ``mvpose demo``: a simulated station measured through the PLC twin."""

from __future__ import annotations

import asyncio
import os
import secrets
import socket
from pathlib import Path

import numpy as np

from drivers.links.layout import Status
from mvpose_core.reasons import describe, reason_name
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import RobotConvention
from server.links import load_station
from server.loopback import Loopback, TriggerRow, move_part, running_station, trigger
from server.pipeline import PipelineOptions, auto_detect_processes
from server.settings import Settings
from server.station.core import StationOptions
from server.validation import TruthWriter


def _free(port: int) -> int:
    """``port`` if it can be bound on loopback, else 0 (any free port)."""
    if port == 0:
        return 0
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            print(f"port {port} is taken; the REST API takes a free port instead")
            return 0
    return port


def _fmt(v: np.ndarray) -> str:
    return " ".join(f"{x:7.2f}" for x in v[:3]) + " |" + " ".join(f"{x:6.2f}" for x in v[3:6])


def _units(conv: RobotConvention) -> tuple[str, str]:
    """The units of the offset columns as the PLC gets them (docs/plc-interface.md)."""
    if conv is RobotConvention.ABB:
        return "mm", "quat."
    if conv is RobotConvention.UR:
        return "mm", "rad"
    return "mm", "deg"


def run_station_demo(
    station_path: str | Path, triggers: int | None, *, keep_serving: bool = False, seed: int = 1,
    port: int = 8000, data_dir: Path = Path("var") / "demo", max_mm: float = 20.0,
    max_deg: float = 2.0, truth: Path | None = None, link: str = "modbus",
) -> int:
    """Run the demo; returns the number of OK results whose error is beyond the tolerances.
    ``link``: the bus the PLC twin talks over (a key of :data:`server.plc_buses.BUSES`)."""
    station = load_station(station_path)  # StationFileError names file, field and value
    if any(c.driver.kind != "sim" for c in station.cameras):
        raise ValueError(f"{station_path}: the demo needs simulated cameras (driver kind: sim)")
    token = os.environ.get("MVPOSE_BOOTSTRAP_TOKEN") or "mvp_demo-" + secrets.token_urlsafe(18)
    settings = Settings(station=Path(station_path), data_dir=data_dir, bootstrap_token=token)
    try:
        return asyncio.run(_demo(settings, triggers, keep_serving, seed, _free(port), token,
                                 max_mm, max_deg, truth, link))
    except KeyboardInterrupt:
        print("\nstopped")
        return 0


async def _demo(settings: Settings, triggers: int | None, keep_serving: bool, seed: int,
                port: int, token: str, max_mm: float, max_deg: float,
                truth: Path | None = None, link: str = "modbus") -> int:
    rng = np.random.default_rng(seed)
    # The pipeline as `mvpose serve` runs it on this machine.
    options = StationOptions(
        sim_seed=seed, pipeline=PipelineOptions(detect_processes=auto_detect_processes()))
    print("starting the station: store, 4 MP simulated cameras, warm-up ...", flush=True)
    async with running_station(settings, options, http_port=port, link=link) as lb:
        rt = lb.runtime
        assert rt.active is not None and rt.services is not None  # started
        recipe = rt.active.config
        tol = recipe.tolerances
        print(f"station {rt.station.name}: {len(rt.station.cameras)} simulated cameras, "
              f"recipe {recipe.name} v{rt.active.version}, deadline {rt.station.deadline_ms:g} ms")
        print(f"REST API  {lb.base_url}/api/v1   (OpenAPI: {lb.base_url}/docs)")
        print(f"token     {token}   (engineer; e.g. curl -H 'Authorization: Bearer {token}' "
              f"{lb.base_url}/api/v1/measurements)")
        assert lb.bus is not None  # running_station opens one
        print(lb.bus.describe(rt))
        print(f"store     {settings.resolved_database_url}")
        conv = recipe.robot_convention
        lin, ang = _units(conv)
        labels = " ".join(f"{x:>7}" for x in conv.labels[:3]) + " |" + " ".join(
            f"{x:>6}" for x in conv.labels[3:6])
        units = " ".join(f"{lin:>7}" for _ in range(3)) + " |" + " ".join(
            f"{ang:>6}" for _ in range(3))
        print(f"\nOffsets in the {conv.value.upper()} convention (what the PLC reads); error = "
              f"measured vs true at the grasp point; 1σ = the station's own estimate there.")
        print(f"{'#':>4}  offset {labels}   error at grasp    1σ at grasp     cycle    result")
        print(f"{'':>4}         {units}   deg       mm      deg       mm     ms")
        first = rt.services.store.measurements.count() + 1
        rows: list[TriggerRow] = []
        bad = nok = 0
        i = 0
        # each row is flushed: a demo stopped with Ctrl-C leaves every answered trigger in it
        writer = TruthWriter(truth, recipe) if truth is not None else None
        while triggers is None or i < triggers:
            T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, max_mm, max_deg)
            await move_part(rt, lb.twin, T)
            row = await _trigger_part(lb, recipe, first + i, T)
            i += 1
            if row is None:
                continue
            rows.append(row)
            if writer is not None:
                ok = row.result_code == 0
                writer.add(row.trigger_id, f"DEMO-{row.trigger_id}", row.true_offset,
                           row.measured_offset if ok else None, reason_name(row.result_code),
                           (row.rot_err_deg, row.trans_err_mm) if ok else None)
            print(f"{row.trigger_id:4d}  true   {_fmt(row.true_offset)}")
            if row.result_code == 0:
                wrong = row.rot_err_deg > tol.rotation_deg or row.trans_err_mm > tol.translation_mm
                bad += wrong
                print(f"      meas.  {_fmt(row.measured_offset)}   {row.rot_err_deg:5.3f}  "
                      f"{row.trans_err_mm:6.3f}    {row.sigma_deg:5.3f}  {row.sigma_mm:6.3f}  "
                      f"{row.server_ms:5.1f}    OK{'  BEYOND TOLERANCE' if wrong else ''}")
            else:
                nok += 1
                msg = rt.last["message"] if rt.last else ""
                print(f"      NOK: {describe(row.result_code)} ({reason_name(row.result_code)}, "
                      f"code {row.result_code}) after {row.server_ms:.1f} ms\n           {msg}")
        _summary(rows, nok)
        if writer is not None:
            writer.close()
            print(f"\ntrue and measured offsets per trigger in {truth} (`mvpose validate "
                  "--truth` reads it)")
        print(f"\nOperator page: {lb.base_url}/  (log in with the token above); REST API "
              f"{lb.base_url}/api/v1; records in {settings.resolved_database_url}")
        if triggers is None or keep_serving:
            print(f"\nOperator page and REST API still up at {lb.base_url}/ — Ctrl-C to stop",
                  flush=True)
            while True:
                await asyncio.sleep(3600)
        return bad


async def _trigger_part(lb: Loopback, recipe: object, tid: int, T: np.ndarray) -> TriggerRow | None:
    """One part: a trigger per view (robot-mounted rigs) or one trigger (fixed cameras)."""
    rt = lb.runtime
    assert rt.active is not None
    rc = rt.active.config
    views = sorted({s.view for s in rc.sightings})
    if not rt.station.robot_mounted:
        return (await trigger(lb.twin, rc, tid, T, part_id=f"DEMO-{tid}"))[1]
    row = None
    for view in views:
        rt.scene.set_view(view)
        status, row = await trigger(lb.twin, rc, tid, T, view_index=view, part_id=f"DEMO-{tid}")
        if status.has(Status.RESULT_VALID):
            return row
    return row


def _summary(rows: list[TriggerRow], nok: int) -> None:
    ok = [r for r in rows if r.result_code == 0]
    if not ok:
        print(f"\n{len(rows)} triggers, {nok} NOK")
        return
    rot = np.array([r.rot_err_deg for r in ok])
    mm = np.array([r.trans_err_mm for r in ok])
    ms = np.array([r.server_ms for r in rows])
    print(f"\n{len(rows)} triggers: {len(ok)} OK, {nok} NOK; error at the grasp RMS "
          f"{np.sqrt(np.mean(rot**2)):.4f}° {np.sqrt(np.mean(mm**2)):.3f} mm (max {rot.max():.4f}° "
          f"{mm.max():.3f} mm); server latency p50 {np.percentile(ms, 50):.1f} ms, "
          f"max {ms.max():.1f} ms")
