"""Commissioning validation: injected grasp-frame errors are recovered, statistics, CSV and CLI."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pytest

from mvpose_core.station import load_station
from mvpose_core.transforms import (
    compose,
    invert,
    make_transform,
    rotvec_to_matrix,
    to_robot,
    xyzwpr_to_matrix,
)
from server.cli import main as cli_main
from server.validation import ValidationError, read_offsets_csv, validate_offsets

ROOT = Path(__file__).resolve().parents[2]
STATION1 = ROOT / "deploy" / "stations" / "station1.yaml"


@pytest.fixture(scope="module")
def recipe():
    return load_station(STATION1).recipe()


def _series(recipe, rng: np.random.Generator, n: int, rot_err_deg: np.ndarray,
            trans_err_mm: np.ndarray):
    """True offsets and measured offsets whose grasp frames differ by the given errors (RF axes)."""
    T_pf0_grasp = compose(recipe.T_rf_from_pf0.matrix, recipe.T_pf_from_grasp.matrix)
    truth, measured = {}, {}
    for i in range(n):
        true = xyzwpr_to_matrix([*rng.uniform(-50, 50, 3), *rng.uniform(-5, 5, 3)])
        G_true = true @ T_pf0_grasp
        err = make_transform(rotvec_to_matrix(np.radians(rot_err_deg[i])), np.zeros(3))
        G_meas = err @ G_true
        G_meas[:3, 3] = G_true[:3, 3] + trans_err_mm[i]
        truth[str(i + 1)] = true
        measured[str(i + 1)] = G_meas @ invert(T_pf0_grasp)
    return truth, measured


def test_injected_errors_are_recovered_per_row_and_in_statistics(recipe) -> None:
    rng = np.random.default_rng(8)
    n = 9
    rot = rng.normal(0.0, 0.1, (n, 3))
    trans = rng.normal(0.2, 0.3, (n, 3))
    truth, measured = _series(recipe, rng, n, rot, trans)
    report = validate_offsets(truth, measured, recipe)
    assert [r.key for r in report.rows] == [str(i + 1) for i in range(n)]
    got_rot = np.array([r.rotation_deg for r in report.rows])
    got_trans = np.array([r.translation_mm for r in report.rows])
    np.testing.assert_allclose(got_rot, rot, atol=1e-9)
    np.testing.assert_allclose(got_trans, trans, atol=1e-9)
    np.testing.assert_allclose(report.translation.mean, trans.mean(axis=0), atol=1e-9)
    np.testing.assert_allclose(report.translation.std, trans.std(axis=0, ddof=1), atol=1e-9)
    np.testing.assert_allclose(report.rotation.rms, np.sqrt((rot**2).mean(axis=0)), atol=1e-9)
    d = np.linalg.norm(trans, axis=1)
    assert report.distance_rms_mm == pytest.approx(np.sqrt(np.mean(d**2)))
    assert report.angle_rms_deg == pytest.approx(np.sqrt(np.mean(np.sum(rot**2, axis=1))))
    # 0.2 mm bias + 0.3 mm noise per axis: total RMS ~0.66 mm, under the 1 mm tolerance.
    assert report.passed == (report.distance_rms_mm <= 1.0 and report.angle_rms_deg <= 0.2)


def test_large_errors_fail_and_missing_rows_are_reported(recipe) -> None:
    rng = np.random.default_rng(3)
    n = 5
    truth, measured = _series(recipe, rng, n, np.zeros((n, 3)), np.full((n, 3), 2.0))
    del measured["3"]
    measured["99"] = measured["1"]
    report = validate_offsets(truth, measured, recipe)
    assert report.missing_measurements == ("3",)
    assert report.unmatched_measurements == ("99",)
    assert len(report.rows) == 4
    assert not report.passed
    text = report.table()
    assert "MISSING measurements for: 3" in text and "FAILED" in text


def _write_csv(path: Path, offsets: dict[str, np.ndarray], key: str, prefix: str = "") -> None:
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow([key, *(prefix + lab for lab in ("X", "Y", "Z", "W", "P", "R")), "note"])
        for k, T in offsets.items():
            w.writerow([k, *(f"{v:.6f}" for v in to_robot(T, "fanuc")), "x"])


def test_cli_reads_both_csv_layouts_and_writes_the_report(recipe, tmp_path, capsys) -> None:
    rng = np.random.default_rng(5)
    n = 6
    rot = rng.normal(0, 0.02, (n, 3))
    trans = rng.normal(0, 0.1, (n, 3))
    truth, measured = _series(recipe, rng, n, rot, trans)
    _write_csv(tmp_path / "truth.csv", truth, "index")
    _write_csv(tmp_path / "measured.csv", measured, "index", prefix="offset_")
    rc = cli_main(["validate", "--station", str(STATION1), "--truth", str(tmp_path / "truth.csv"),
                   "--measured", str(tmp_path / "measured.csv"), "--out", str(tmp_path / "r.csv")])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "PASSED" in out
    rows = list(csv.DictReader(io.StringIO((tmp_path / "r.csv").read_text())))
    assert [r["index"] for r in rows] == [str(i + 1) for i in range(n)]
    # 6 decimals in the CSV: the recovered errors agree to well under a micron / micro-degree.
    np.testing.assert_allclose([float(r["x_mm"]) for r in rows], trans[:, 0], atol=1e-4)
    np.testing.assert_allclose([float(r["rot_z_deg"]) for r in rows], rot[:, 2], atol=1e-4)


def test_bad_csv_names_file_line_column_and_value(recipe, tmp_path, capsys) -> None:
    bad = tmp_path / "truth.csv"
    bad.write_text("index,X,Y,Z,W,P,R\n1,0,0,0,0,0,0\n2,0,abc,0,0,0,0\n")
    with pytest.raises(ValidationError, match=r"truth\.csv: line 3: column 'Y' .*'abc'"):
        read_offsets_csv(bad, recipe)
    nokey = tmp_path / "nokey.csv"
    nokey.write_text("X,Y,Z,W,P,R\n0,0,0,0,0,0\n")
    with pytest.raises(ValidationError, match="no key column"):
        read_offsets_csv(nokey, recipe)
    short = tmp_path / "short.csv"
    short.write_text("index,X,Y,Z,W,P\n1,0,0,0,0,0\n")
    with pytest.raises(ValidationError, match=r"missing \['R'\]"):
        read_offsets_csv(short, recipe)
    rc = cli_main(["validate", "--station", str(STATION1), "--truth", str(bad),
                   "--measured", str(bad)])
    assert rc == 2
    assert "line 3" in capsys.readouterr().err
