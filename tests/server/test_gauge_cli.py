"""``mvpose gauge``: studies of stored measurements, files and stored studies; their reports and
their records in the audit trail."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from gauge_data import TRUE, store_repeats

from server.cli import main
from server.store import open_store

STATION = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"


@pytest.fixture
def data_dir(tmp_path: Path) -> Path:
    d = tmp_path / "var"
    d.mkdir()
    store = open_store(f"sqlite:///{d / 'mvpose.db'}", "station1")
    rng = np.random.default_rng(11)
    store_repeats(store, rng, "VIN-GAUGE", 30)
    for k, part in enumerate(["P1", "P2", "P3", "P4", "P5"]):
        true = np.asarray(TRUE) + np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 0.03, 3)]
        store_repeats(store, rng, part, 3, true, first_trigger=100 + 10 * k)
    store.close()
    return d


def _gauge(*args: str) -> int:
    return main(["gauge", *args, "--station", str(STATION)])


def test_type1_on_stored_measurements_writes_reports_and_a_chained_record(
        data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    ref = ",".join(str(v) for v in TRUE)
    code = _gauge("type1", "--data-dir", str(data_dir), "--part-id", "VIN-GAUGE",
                  "--reference", ref, "--out", str(out), "--by", "qe")
    text = capsys.readouterr().out
    assert code == 0, text
    assert "PASSED (study 1 in the audit trail)" in text
    html = (out / "report.html").read_text()
    assert "Type-1 gauge study" in html and html.count("<svg") == 10  # 6 axes, grasp X Y Z, |dT|
    assert "PASSED" in html and "quality engineer" in html
    assert (out / "report.pdf").read_bytes().startswith(b"%PDF")
    body = json.loads((out / "study.json").read_text())
    assert [f["name"] for f in body["figures"]][:3] == ["X", "Y", "Z"]
    assert all(f["cg"] >= 1.33 and f["cgk"] >= 1.33 for f in body["figures"])
    assert len(body["records"]) == 30
    store = open_store(f"sqlite:///{data_dir / 'mvpose.db'}", "station1")
    try:
        stored = store.gauge.newest()
        assert [s.seq for s in stored] == [1] and stored[0].created_by == "qe"
        assert store.gauge.verify() == []
    finally:
        store.close()
    # the stored study's report again, from its record
    again = tmp_path / "again"
    assert _gauge("type1", "--data-dir", str(data_dir), "--study", "1", "--out", str(again)) == 0
    assert stored[0].hash in (again / "report.html").read_text()


def test_type1_fails_against_a_tight_tolerance(data_dir: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    code = _gauge("type1", "--data-dir", str(data_dir), "--part-id", "VIN-GAUGE",
                  "--tolerance-mm", "0.05", "--out", str(tmp_path / "r"))
    text = capsys.readouterr().out
    assert code == 1 and "FAILED" in text and "NOT capable" in text
    assert "Cg only: no reference" in text


def test_type1_refuses_several_parts_and_too_few_repeats(
        data_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _gauge("type1", "--data-dir", str(data_dir), "--out", str(tmp_path / "r")) == 2
    assert "a type-1 study measures one part" in capsys.readouterr().err
    assert _gauge("type1", "--data-dir", str(data_dir), "--part-id", "P1",
                  "--out", str(tmp_path / "r")) == 2
    assert "at least 25 measurements of one part, got 3" in capsys.readouterr().err


def test_type3_on_stored_parts(data_dir: Path, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "t3"
    code = _gauge("type3", "--data-dir", str(data_dir), "--since", "2026-01-01T00:00:00",
                  "--ids", ",".join(str(i) for i in range(31, 46)), "--out", str(out))
    text = capsys.readouterr()
    assert code in (0, 1), text.err
    body = json.loads((out / "study.json").read_text())
    first = body["figures"][0]
    assert first["n_parts"] == 5 and first["repeats"] == 3 and first["spread"] == 6.0
    assert body["characteristics"][0]["parts"] == ["P1", "P2", "P3", "P4", "P5"]


def test_linearity_from_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(5)
    truth = tmp_path / "truth.csv"
    meas = tmp_path / "measured.csv"
    rows_t = ["key,X,Y,Z,W,P,R"]
    rows_m = ["key,X,Y,Z,W,P,R"]
    for k in range(20):
        t = np.r_[rng.uniform(-10, 10, 3), rng.uniform(-1, 1, 3)]
        m = t + np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 0.002, 3)]
        rows_t.append(f"{k}," + ",".join(f"{v:.6f}" for v in t))
        rows_m.append(f"{k}," + ",".join(f"{v:.6f}" for v in m))
    truth.write_text("\n".join(rows_t) + "\n")
    meas.write_text("\n".join(rows_m) + "\n")
    out = tmp_path / "lin"
    code = _gauge("linearity", "--measured", str(meas), "--truth", str(truth), "--out", str(out))
    text = capsys.readouterr()
    assert code in (0, 1), text.err
    body = json.loads((out / "study.json").read_text())
    assert body["kind"] == "linearity" and body["records"] == []
    assert all(abs(f["slope"]) < 0.01 for f in body["figures"])
    assert (out / "report.pdf").read_bytes().startswith(b"%PDF")


def test_no_measurements_is_a_clear_error(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert _gauge("type1", "--out", str(tmp_path / "r")) == 2
    assert "give the measurements" in capsys.readouterr().err


def test_linearity_on_an_image_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from test_measure_cli import render_triggers

    images = tmp_path / "images"
    render_triggers("station1", images, 4, seed=8)
    out = tmp_path / "lin"
    code = _gauge("linearity", "--images", str(images), "--truth",
                  str(tmp_path / "station1-truth.csv"), "--key", "part_id", "--out", str(out))
    text = capsys.readouterr()
    assert code in (0, 1), text.err
    body = json.loads((out / "study.json").read_text())
    assert body["source"]["images"] == str(images)
    assert body["source"]["keys"] == ["part001", "part002", "part003", "part004"]
    assert (out / "measured" / "measurements.csv").is_file()
    # measured against the rendered truth: the bias stays far below a tenth of a millimetre
    x = body["characteristics"][0]
    assert max(abs(m - r) for m, r in zip(x["values"], x["reference"], strict=True)) < 0.1
