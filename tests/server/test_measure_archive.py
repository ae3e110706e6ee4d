"""``mvpose measure --from-archive``: the data folder a real station run wrote, measured again."""

from __future__ import annotations

import asyncio
import csv
import json
from pathlib import Path

import numpy as np
import pytest
from stations import relaxed_deadline, runtime_options, settings_for, station_file

from drivers.links.layout import Status
from mvpose_core.synth import random_displacement
from server.cli import main
from server.loopback import move_part, running_station, trigger
from server.store.schemas import MeasurementFilter, MeasurementRecord

pytestmark = pytest.mark.timeout(600)


async def _station_run(tmp_path: Path, n: int) -> tuple[Path, Path, list[dict[str, object]]]:
    """Station 1 on simulated cameras, every trigger's frames archived (images_ok_every=1):
    ``n`` parts at random displacements over Modbus; its station file, data folder and records."""
    station = station_file(tmp_path, "station1", relaxed_deadline)
    data = tmp_path / "var"
    settings = settings_for(station, data).model_copy(update={"images_ok_every": 1})
    async with running_station(settings, runtime_options(7), http_port=None) as lb:
        recipe = lb.runtime.active.config
        rng = np.random.default_rng(7)
        for tid in range(1, n + 1):
            T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, 10.0, 1.0)
            await move_part(lb.runtime, lb.twin, T)
            status, _ = await trigger(lb.twin, recipe, tid, None, part_id=f"BODY-{tid}")
            assert status.has(Status.RESULT_VALID)
            # an OK trigger's frames are kept only while no other trigger's wait to be written
            await asyncio.to_thread(lb.runtime.wait_idle)
        store = lb.runtime.services.store
        stored = [m.model_dump(mode="json")
                  for m in store.measurements.iterate(MeasurementFilter())]
        assert all(store.images.for_measurement(m["id"]) for m in stored)
    return station, data, stored


async def test_the_archive_a_station_wrote_measures_as_the_station_did(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    station, data, stored = await _station_run(tmp_path, 3)
    assert [m["record"]["result"] for m in stored] == ["OK"] * 3
    out = tmp_path / "measured"
    assert await asyncio.to_thread(main, ["measure", "--station", str(station), "--from-archive",
                                          str(data), "--out", str(out), "--quiet"]) == 0
    assert "3 triggers: 3 OK, 0 NOK" in capsys.readouterr().out
    with (out / "measurements.csv").open(newline="") as f:
        rows = list(csv.DictReader(f))
    records = [MeasurementRecord.model_validate(r)
               for r in json.loads((out / "measurements.json").read_text())]
    # keyed by result id, with the record's trigger id, part id and trigger time
    assert [r["key"] for r in rows] == [str(m["seq"]) for m in stored]
    assert [r["part_id"] for r in rows] == ["BODY-1", "BODY-2", "BODY-3"]
    assert [r["trigger_id"] for r in rows] == ["1", "2", "3"]
    for m, rec in zip(stored, records, strict=True):
        orig = MeasurementRecord.model_validate(m["record"])
        assert rec.triggered_at == orig.triggered_at and rec.part_id == orig.part_id
        assert orig.offset is not None and rec.offset is not None
        # the same frames through the same pipeline: the station's offset
        np.testing.assert_allclose(rec.offset.values, orig.offset.values, atol=1e-6)

    # a result id range and a time selects records; the rest are not measured
    part = tmp_path / "part"
    assert await asyncio.to_thread(main, [
        "measure", "--station", str(station), "--from-archive", str(data), "--result-ids",
        f"{stored[1]['seq']}-{stored[2]['seq']}", "--out", str(part), "--quiet"]) == 0
    assert "2 triggers: 2 OK" in capsys.readouterr().out
    later = stored[2]["record"]["triggered_at"]
    assert await asyncio.to_thread(main, [
        "measure", "--station", str(station), "--from-archive", str(data), "--since",
        str(later), "--out", str(part), "--quiet"]) == 0
    assert "1 triggers: 1 OK" in capsys.readouterr().out

    # an evicted frame fails its camera of that record alone, naming the file
    first = next((data / "images").rglob("*-1-*-v1-top_left.png"))
    first.unlink()
    assert await asyncio.to_thread(main, ["measure", "--station", str(station), "--from-archive",
                                          str(data), "--out", str(out), "--quiet"]) == 0
    assert "3 triggers: 2 OK, 1 NOK" in capsys.readouterr().out
    bad = json.loads((out / "measurements.json").read_text())[0]
    assert "top_left" in bad["message"] and "missing" in bad["message"]

    # bad selections are one line each
    for args, what in ((["--result-ids", "9-2"], "runs backwards"),
                       (["--result-ids", "x"], "--result-ids"),
                       (["--result-ids", "900-999"], "no stored record")):
        assert main(["measure", "--station", str(station), "--from-archive", str(data),
                     *args, "--quiet"]) == 2
        assert what in capsys.readouterr().err
    assert main(["measure", "--station", str(station), "--from-archive",
                 str(tmp_path / "nowhere")]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert main(["measure", "--station", str(station), "--images", str(tmp_path),
                 "--result-ids", "1"]) == 2
    assert "only with --from-archive" in capsys.readouterr().err
