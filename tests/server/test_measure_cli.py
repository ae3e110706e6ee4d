"""``mvpose measure`` on rendered images with known truth, then ``mvpose validate`` on it."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from mvpose_core.reasons import Reason
from mvpose_core.render import render_view
from mvpose_core.scene import sighted_marks, view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import invert, to_robot, transform_error
from server.cli import main
from server.store.schemas import MeasurementRecord

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"


def render_triggers(name: str, root: Path, n: int, seed: int) -> tuple[dict[str, np.ndarray], Path]:
    """``root/part00k[/v<view>]/<camera>.png`` for n displaced parts, and a truth CSV."""
    st = load_station(STATIONS / f"{name}.yaml")
    rec = st.recipe()
    rng = np.random.default_rng(seed)
    several = st.robot_mounted
    truth: dict[str, np.ndarray] = {}
    rows = []
    for k in range(1, n + 1):
        T = rec.T_rf_from_pf0.matrix @ random_displacement(rng, 10.0, 1.0)
        key = f"part{k:03d}"
        for cam in view_cameras(st):
            if not sighted_marks(rec, cam.view, cam.camera_id):
                continue
            folder = root / key / (f"v{cam.view}" if several else "")
            folder.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(folder / f"{cam.camera_id}.png"),
                               render_view(cam, rec, T, rng).image)
        truth[key] = T
        rows.append([key, *to_robot(T @ invert(rec.T_rf_from_pf0.matrix), rec.robot_convention)])
    truth_csv = root.parent / f"{name}-truth.csv"
    with truth_csv.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["part_id", *rec.robot_convention.labels])
        w.writerows(rows)
    return truth, truth_csv


def read_rows(path: Path) -> dict[str, dict[str, str]]:
    with path.open(newline="") as f:
        return {r["key"]: r for r in csv.DictReader(f)}


def test_fixed_station_a_missing_image_fails_its_trigger_alone(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = tmp_path / "st1"
    truth, truth_csv = render_triggers("station1", images, 3, seed=3)
    (images / "part002" / "top_left.png").unlink()  # one camera's file of one trigger
    station = STATIONS / "station1.yaml"
    assert main(["measure", "--station", str(station), "--images", str(images), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "3 triggers: 2 OK, 1 NOK" in out
    rows = read_rows(images / "measured" / "measurements.csv")
    assert [rows[k]["result"] for k in ("part001", "part002", "part003")] == ["OK", "NOK", "OK"]
    bad = rows["part002"]
    assert int(bad["reason_code"]) == Reason.CAMERA_FAILED
    assert "top_left" in bad["message"] and "top_left.png" in bad["message"]
    assert bad["X"] == ""  # a NOK result carries no offset
    records = [MeasurementRecord.model_validate(r) for r in
               json.loads((images / "measured" / "measurements.json").read_text())]
    assert [r.part_id for r in records] == ["part001", "part002", "part003"]
    rec = load_station(station).recipe()
    for r in records:
        if r.result == "OK":
            assert r.T_rf_from_pf is not None
            deg, mm = transform_error(np.array(r.T_rf_from_pf) @ rec.T_pf_from_grasp.matrix,
                                      truth[r.part_id or ""] @ rec.T_pf_from_grasp.matrix)
            assert deg < 0.01 and mm < 0.05
            row = rows[r.part_id or ""]
            # both parts of the 1σ are reported; no calibration 1σ is set for station 1
            assert float(row["sigma_detector_mm"]) > 0 and float(row["sigma_calibration_mm"]) == 0
            assert float(row["sigma_mm"]) == pytest.approx(r.uncertainty.sigma_mm)  # type: ignore[union-attr]

    # validate reads the output without options (key: part_id, common to both files); the
    # NOK trigger is reported missing, so the run does not pass ...
    args = ["validate", "--station", str(station), "--truth", str(truth_csv)]
    assert main([*args, "--measured", str(images / "measured" / "measurements.csv")]) == 1
    assert "part002" in capsys.readouterr().out
    # ... and passes on the triggers that were measured, from the CSV and from the JSON
    lines = truth_csv.read_text().splitlines()
    truth_csv.write_text("\n".join(line for line in lines if "part002" not in line) + "\n")
    for name in ("measurements.csv", "measurements.json"):
        assert main([*args, "--measured", str(images / "measured" / name)]) == 0
        assert "PASSED" in capsys.readouterr().out


def test_robot_rig_views_in_subfolders_with_the_flange_pose(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = tmp_path / "lab"
    truth, truth_csv = render_triggers("lab", images, 2, seed=5)
    st = load_station(STATIONS / "lab.yaml")
    v2 = st.view(2).T_rf_from_gf
    assert v2 is not None
    # the taught flange pose, written as the robot's own values: the same measurement
    (images / "part001" / "v2" / "flange.yaml").write_text(
        "convention: fanuc\nvalues: [" + ", ".join(
            repr(float(x)) for x in to_robot(v2.matrix, "fanuc")) + "]\n")
    out_dir = tmp_path / "out"
    assert main(["measure", "--station", str(STATIONS / "lab.yaml"), "--images", str(images),
                 "--out", str(out_dir), "--quiet"]) == 0
    assert "2 triggers: 2 OK, 0 NOK" in capsys.readouterr().out
    assert main(["validate", "--station", str(STATIONS / "lab.yaml"), "--truth", str(truth_csv),
                 "--measured", str(out_dir / "measurements.csv")]) == 0


def test_bad_input_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    station = str(STATIONS / "station1.yaml")
    assert main(["measure", "--station", station, "--images", str(tmp_path / "none")]) == 2
    assert "no such folder" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["measure", "--station", station, "--images", str(tmp_path / "empty")]) == 2
    assert "no trigger folders" in capsys.readouterr().err


def test_a_frame_of_the_wrong_size_is_refused_naming_camera_and_formats(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    images = tmp_path / "st1"
    render_triggers("station1", images, 1, seed=5)
    path = images / "part001" / "top_right.png"
    frame = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert cv2.imwrite(str(path), cv2.resize(frame, (2560, 2560)))  # rescaled: never cropped
    station = STATIONS / "station1.yaml"
    assert main(["measure", "--station", str(station), "--images", str(images), "--quiet"]) == 0
    capsys.readouterr()
    row = read_rows(images / "measured" / "measurements.csv")["part001"]
    assert int(row["reason_code"]) == Reason.DETECTION_FAILED
    assert "top_right" in row["message"] and "2560x2560" in row["message"]
    assert "2048x2048" in row["message"] and row["X"] == ""
