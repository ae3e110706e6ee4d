"""``mvpose replay``: archived measurements re-measured with another calibration, side by side."""

from __future__ import annotations

import csv
import json
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest
from test_measure_cli import STATIONS, render_triggers

from drivers.cameras import Frame
from drivers.cameras.files import read_image
from mvpose_core.calibration.files import (
    InputsSummary,
    RigCalibration,
    make_calibration,
    pose,
    save_calibration,
)
from mvpose_core.station import load_station
from mvpose_core.transforms import make_transform
from server.cli import main
from server.commands.offline import OfflineStation
from server.images import ImageArchive
from server.recipes import ActiveRecipe
from server.state import seed_recipes
from server.store import open_store


def archive_measurements(tmp_path: Path) -> Path:
    """A station-1 data folder whose store holds 2 measurements of rendered parts (frames
    archived), measured as the station measures them; returns the data folder."""
    images = tmp_path / "shots"
    render_triggers("station1", images, 2, seed=9)
    station = load_station(STATIONS / "station1.yaml")
    data = tmp_path / "var"
    data.mkdir()
    store = open_store(f"sqlite:///{(data / 'mvpose.db').as_posix()}", station.name)
    try:
        seed_recipes(store, station, "test")
        rc = station.recipe()
        info, _ = store.versions.content("recipe", rc.name)
        active = ActiveRecipe(rc.model_copy(update={"version": info.version}), info.version,
                              info.sha256, 1)
        archive = ImageArchive(data / "images", store.images, ok_every=1, quota_bytes=10**9)
        offline = OfflineStation(station, active, None)
        cams = [(1, cid) for cid in station.view_camera_ids(1)]
        for n, folder in enumerate(sorted(p for p in images.iterdir() if p.is_dir()), start=1):
            pics = {(v, cid): read_image(folder / f"{cid}.png", cid) for v, cid in cams}
            frames = {k: Frame(k[1], img, 0, float("nan"), float("nan")) for k, img in pics.items()}
            when = datetime(2026, 11, 23, 12, n, tzinfo=UTC)
            o = offline.measure(folder.name, n, frames, triggered_at=when)
            refs = archive.plan(station.name, n, when, o.record.result == "OK", cams)
            stored = store.measurements.insert(o.record.model_copy(update={"images": refs}))
            archive.write(stored.id, refs, o.record.result == "OK", pics)
        offline.close()
    finally:
        store.close()
    return data


def rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_replay_with_a_moved_rig_shows_the_shift_beside_the_original(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = archive_measurements(tmp_path)
    station = STATIONS / "station1.yaml"
    # the same station and calibration: the same results
    same = tmp_path / "same"
    assert main(["replay", "--station", str(station), "--data-dir", str(data), "--out",
                 str(same), "--quiet"]) == 0
    assert "2 measurements, 0 without archived frames" in capsys.readouterr().out
    for r in rows(same / "replay.csv"):
        assert r["orig_result"] == r["result"] == "OK"
        assert float(r["diff_mm"]) < 1e-6 and float(r["diff_deg"]) < 1e-7
        assert r["X"] == r["orig_X"]
    # a calibration that puts the whole camera rig 1 mm further along X in the robot base
    st = load_station(station)
    rig = st.rigs[0]
    assert rig.T_rf_from_rig is not None
    moved = make_transform(np.eye(3), [1.0, 0.0, 0.0]) @ rig.T_rf_from_rig.matrix
    calib = make_calibration("station", InputsSummary(board="test"), station=st.name,
                             rigs={rig.id: RigCalibration(T_rf_from_rig=pose(moved))})
    cal_file = save_calibration(tmp_path / "moved.json", calib)
    out = tmp_path / "moved"
    assert main(["replay", "--station", str(station), "--data-dir", str(data), "--calibration",
                 str(cal_file), "--out", str(out), "--quiet"]) == 0
    got = rows(out / "replay.csv")
    assert [r["key"] for r in got] == ["part001", "part002"]
    for r in got:
        assert r["calibration_id"] == calib.id and r["orig_calibration_id"] == ""
        assert float(r["diff_mm"]) == pytest.approx(1.0, abs=0.01)
        assert float(r["X"]) - float(r["orig_X"]) == pytest.approx(1.0, abs=0.01)
    replayed = json.loads((out / "replay.json").read_text())
    assert [x["replayed"]["calibration_id"] for x in replayed] == [calib.id, calib.id]


def test_replay_names_what_is_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    station = str(STATIONS / "station1.yaml")
    assert main(["replay", "--station", station, "--data-dir", str(tmp_path / "nothing")]) == 2
    assert "no store (mvpose.db)" in capsys.readouterr().err
