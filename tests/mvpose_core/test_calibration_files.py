"""Calibration files (hash, load/save, apply to a station) and reports (outliers, LOO, plot)."""

from __future__ import annotations

import json
import re
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from mvpose_core.calibration.files import (
    CalibrationFileError,
    CameraCalibration,
    InputsSummary,
    RigCalibration,
    apply_calibration,
    load_calibration,
    make_calibration,
    pose,
    save_calibration,
)
from mvpose_core.calibration.handeye import build_problem, calibrate_handeye
from mvpose_core.calibration.report import find_outliers, handeye_report, save_residual_plot
from mvpose_core.calibration.synthetic import lab_camera, make_scene
from mvpose_core.station import load_station
from mvpose_core.transforms import make_transform, transform_error, zyx_to_matrix

LAB = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "lab.yaml"
WHEN = datetime(2026, 11, 21, 12, 0, 0, tzinfo=UTC)


def _calib() -> object:
    cam = lab_camera()
    T = make_transform(zyx_to_matrix(90.0, 0.3, -0.2), [1.5, 121.0, 179.0])
    return make_calibration(
        "handeye",
        InputsSummary(
            board="chessboard:11x8:35",
            samples_used=["001", "002"],
            samples_rejected={"003": "board not found"},
        ),
        cameras={"left": CameraCalibration.from_model(cam)},
        rigs={"stereo": RigCalibration(T_gf_from_rig=pose(T))},
        report={"rms_px": np.float64(0.12), "per_sample": {"001": 0.1}},
        station="lab",
        created=WHEN,
    )


def test_hash_is_canonical_and_stable(tmp_path: Path) -> None:
    a = _calib()
    b = _calib()
    assert a.sha256 == b.sha256 and len(a.sha256) == 64
    assert a.id == "lab-handeye-20261121T120000Z"
    p = save_calibration(tmp_path / "c.json", a)
    loaded = load_calibration(p)
    assert loaded.ref == a.ref
    # Re-indented, reordered JSON has the same content hash.
    data = json.loads(p.read_text())
    p.write_text(json.dumps(data, indent=None, sort_keys=False))
    assert load_calibration(p).sha256 == a.sha256


def test_edited_file_is_rejected(tmp_path: Path) -> None:
    p = save_calibration(tmp_path / "c.json", _calib())
    data = json.loads(p.read_text())
    data["cameras"]["left"]["intrinsics"]["fx"] += 1.0
    p.write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match="edited after it was written"):
        load_calibration(p)
    p.write_text('{"format": "something-else"}')
    with pytest.raises(CalibrationFileError, match="not an mvpose-calibration/1 file"):
        load_calibration(p)


def test_apply_calibration_replaces_only_what_was_calibrated() -> None:
    station = load_station(LAB)
    cal = _calib()
    out = apply_calibration(station, cal)
    assert out.camera("left").intrinsics == cal.cameras["left"].intrinsics
    assert out.camera("right").intrinsics == station.camera("right").intrinsics
    T_new = out.rig("stereo").T_gf_from_rig.matrix
    assert transform_error(T_new, cal.rigs["stereo"].T_gf_from_rig.matrix) == pytest.approx(
        (0.0, 0.0), abs=1e-9
    )
    assert out.rig("stereo").cameras == station.rig("stereo").cameras


def test_apply_calibration_names_what_does_not_fit() -> None:
    station = load_station(LAB)
    cal = _calib()
    wrong = cal.model_copy(update={"cameras": {"top": cal.cameras["left"]}})
    with pytest.raises(CalibrationFileError, match="camera 'top' is not in station 'lab'"):
        apply_calibration(station, wrong)
    fixed = cal.model_copy(
        update={"rigs": {"stereo": RigCalibration(T_rf_from_rig=pose(np.eye(4)))}}
    )
    with pytest.raises(CalibrationFileError, match="is robot-mounted"):
        apply_calibration(station, fixed)


def test_outliers_are_flagged_and_a_clean_set_is_not() -> None:
    clean = {f"{k:03d}": 0.14 + 0.01 * np.sin(k) for k in range(15)}
    assert find_outliers(clean) == []
    bad = dict(clean, **{"007": 0.6})
    assert find_outliers(bad) == ["007"]


def test_handeye_report_with_a_bad_robot_pose(tmp_path: Path) -> None:
    rng = np.random.default_rng(21)
    scene = make_scene(rng, n_poses=12, stereo=False)
    poses = dict(scene.robot_poses)
    # Sample 004's robot pose was recorded 1.5 mm off: it is left out, and named.
    poses["004"] = poses["004"] @ make_transform(np.eye(3), [1.5, 0.0, 0.0])
    det = scene.observe(rng, 0.1)
    problem, _ = build_problem("robot", scene.board, scene.cameras, poses, det)
    result = calibrate_handeye(problem)
    assert list(result.left_out) == ["004"]
    assert re.match(r"robot pose off the fit by 1\.\d+ mm", result.left_out["004"])
    assert "004" not in result.per_sample_rms_px
    assert transform_error(result.X, scene.X)[1] < 0.3
    rep = handeye_report(problem, result)
    assert rep.rejected["004"].startswith("outlier: robot pose off the fit")
    assert rep.repeatability is not None and rep.repeatability.n == 11
    assert rep.error_mm_at_working_distance == pytest.approx(
        rep.rms_px * result.depth_mm / result.cameras["left"].fx
    )
    png = save_residual_plot(tmp_path / "r.png", rep, result.residuals)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    text = rep.text()
    assert "left out sample 004: outlier: robot pose off the fit" in text
    assert "WARNING left out outlier samples 004" in text
    # The 1σ of the weighted adjustment comes first, the jackknife after it.
    lines = [ln for ln in text.splitlines() if "1σ T_gf_from_cf translation mm" in ln]
    assert len(lines) == 2 and "(jackknife)" in lines[1]


def test_station_file_refers_to_its_calibration(tmp_path: Path) -> None:
    from mvpose_core.calibration.files import calibrated_station
    from mvpose_core.station import dump_station, parse_station

    save_calibration(tmp_path / "cal" / "lab.json", _calib())
    station = load_station(LAB).model_copy(update={"calibration": "cal/lab.json"})
    (tmp_path / "lab.yaml").write_text(dump_station(station))
    reloaded = load_station(tmp_path / "lab.yaml")
    applied, ref = calibrated_station(reloaded, tmp_path / "lab.yaml")
    assert ref == _calib().ref
    assert applied.camera("left").intrinsics == _calib().cameras["left"].intrinsics
    other = parse_station({**reloaded.model_dump(mode="json"), "name": "other"})
    with pytest.raises(CalibrationFileError, match="for station 'lab', not 'other'"):
        calibrated_station(other, tmp_path / "lab.yaml")


def test_weighted_sigma_sees_robot_pose_errors() -> None:
    """0.2 mm / 0.02° robot pose errors, stated as such: the adjustment's 1σ (shown first)
    matches the real spread, and so does the jackknife beside it."""
    from mvpose_core.calibration.handeye import HandEyeOptions
    from mvpose_core.transforms import compose, rotvec_to_matrix

    rng = np.random.default_rng(5)
    scene = make_scene(rng, n_poses=12, stereo=False)
    opt = HandEyeOptions(refine_intrinsics=False, robot_sigma_mm=0.2, robot_sigma_deg=0.02)
    errs, cov, jack = [], [], []
    for _ in range(10):
        det = scene.observe(rng, 0.1)
        noisy = {
            s: compose(
                A,
                make_transform(
                    rotvec_to_matrix(rng.normal(0, np.radians(0.02), 3)), rng.normal(0, 0.2, 3)
                ),
            )
            for s, A in scene.robot_poses.items()
        }
        problem, _ = build_problem("robot", scene.board, scene.cameras, noisy, det)
        result = calibrate_handeye(problem, opt)
        rep = handeye_report(problem, result)
        errs.append(transform_error(result.X, scene.X))
        cov.append((result.sigma_deg, result.sigma_mm))
        jack.append(
            (
                rep.sigma["T_gf_from_cf rotation deg (jackknife)"],
                rep.sigma["T_gf_from_cf translation mm (jackknife)"],
            )
        )
    spread = np.sqrt(np.mean(np.square(errs), axis=0))
    for figure in (cov, jack):
        ratio = spread / np.mean(figure, axis=0)
        assert np.all(ratio > 1 / 1.5) and np.all(ratio < 1.5), (spread, np.mean(figure, axis=0))


def test_report_values_carry_the_digits_their_sigma_needs() -> None:
    from mvpose_core.calibration.report import rounded

    assert rounded(2911.51234, 0.45) == 2911.51
    assert rounded(250.001312, 0.0004) == 250.00131
    assert rounded(179.4123, 2.6) == 179.4
    assert rounded(1.23456, float("nan")) == 1.23456  # no σ: as held
