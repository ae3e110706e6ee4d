"""The engine demo: every simulated displacement is measured OK and printed true vs estimated."""

from __future__ import annotations

import re

from server.cli import main
from server.commands.demo import run_engine_demo


def test_engine_demo_measures_every_displacement() -> None:
    lines: list[str] = []
    assert run_engine_demo(n=3, seed=5, out=lines.append) == 0
    true_rows = [ln for ln in lines if re.match(r"\s*\d+\s+true ", ln)]
    est_rows = [ln for ln in lines if ln.lstrip().startswith("est ")]
    assert len(true_rows) == len(est_rows) == 6  # 3 per station, lab and station1
    assert all(ln.rstrip().endswith("OK") for ln in est_rows)
    errors_mm = [float(m.group(1)) for ln in est_rows if (m := re.search(r"°\s+([\d.]+) mm", ln))]
    assert len(errors_mm) == 6 and max(errors_mm) < 1.0


def test_demo_cli_reports_a_bad_station_file(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\n")
    assert main(["demo", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err


def test_the_engine_demo_has_no_truth_file_to_write(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    assert main(["demo", "--engine-only", "--truth-out", str(tmp_path / "t.csv")]) == 2
    assert "--truth-out is for the server demo" in capsys.readouterr().err
    assert not (tmp_path / "t.csv").exists()
