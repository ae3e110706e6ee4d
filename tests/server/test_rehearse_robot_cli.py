"""``mvpose calibrate rehearse-handeye`` and ``rehearse-verify`` refuse what they cannot
rehearse with one line naming the file or option and the problem, before a station starts.
The rehearsals themselves run in tests/server/test_calibration_walkthrough.py (as the guide
writes them) and, through every link, in tests/server/test_handeye_session.py."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from server.cli import main

ROOT = Path(__file__).resolve().parents[2]
LAB = ROOT / "deploy" / "stations" / "lab.yaml"


def _set(root: Path, poses: str = "id,X,Y,Z,W,P,R\n001,1,2,3,4,5,6\n", **truth: object) -> Path:
    """A set's files as `mvpose calibrate synthetic` writes them (no images needed here)."""
    root.mkdir()
    data = {"station": "lab", "rig": "stereo", "board": "charuco:15x11:40:30",
            "convention": "fanuc", "image_scale": 0.5, "T_gf_from_rig": np.eye(4).tolist(),
            **truth}
    (root / "truth.json").write_text(json.dumps(data))
    (root / "poses.csv").write_text(poses)
    return root


def _handeye(tmp: Path, set_dir: Path, *extra: str, station: Path = LAB) -> int:
    return main(["calibrate", "rehearse-handeye", "--station", str(station), "--set",
                 str(set_dir), "--data-dir", str(tmp / "cell"), *extra])


def test_a_folder_that_is_no_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _handeye(tmp_path, tmp_path / "nowhere") == 2
    assert "nowhere/truth.json" in capsys.readouterr().err
    fixed = _set(tmp_path / "fixed", T_gf_from_rig=None)
    (fixed / "truth.json").write_text(json.dumps({"T_rf_from_cf": {}}))
    assert _handeye(tmp_path, fixed) == 2
    assert "not the truth of a robot-mounted rig's set" in capsys.readouterr().err
    assert not (tmp_path / "cell").exists()


def test_poses_and_station_must_be_the_sets(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    bad = _set(tmp_path / "bad", poses="id,X,Y,Z\n001,1,2,3\n")
    assert _handeye(tmp_path, bad) == 2
    err = capsys.readouterr().err
    assert "poses.csv" in err and "id,X,Y,Z,W,P,R" in err, err
    good = _set(tmp_path / "good")
    station1 = ROOT / "deploy" / "stations" / "station1.yaml"
    assert _handeye(tmp_path, good, station=station1) == 2
    err = capsys.readouterr().err
    assert "rendered for station 'lab'" in err and "'station1'" in err, err
    assert _handeye(tmp_path, good, "--holdout", "51") == 2
    assert "--holdout must be 0..50, got 51" in capsys.readouterr().err


def test_verify_names_the_missing_station_file(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["calibrate", "rehearse-verify", "--station", str(tmp_path / "station.yaml"),
                 "--data-dir", str(tmp_path), "--activate", "1"])
    assert code == 2
    assert "station.yaml: no such file (rehearse-handeye writes" in capsys.readouterr().err
