"""``mvpose simulate``: study files (CSV + PNG), determinism, planning output, one-line errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from mvpose_core.simulation.studies import get_study
from server.cli import main
from server.simulation_output import read_csv

ROOT = Path(__file__).resolve().parents[2]
STATIONS = sorted((ROOT / "deploy" / "stations").glob("*.yaml"))


def test_study_writes_csv_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        [
            "simulate",
            "noise",
            "--trials",
            "6",
            "--seed",
            "3",
            "--out",
            str(tmp_path),
            "--workers",
            "1",
            "--no-progress",
        ]
    )
    assert rc == 0
    rows = read_csv(tmp_path / "noise.csv")
    study = get_study("noise")
    assert len(rows) == 2 * len(study.points)
    assert {r.objective for r in rows} == {"all", "left_only"}
    assert sorted({r.x for r in rows}) == sorted(p.x for p in study.points)
    assert all(
        r.trials == 6 and r.failed == 0 and r.rot_rms > 0 and r.bound_trans > 0 for r in rows
    )
    png = (tmp_path / "noise.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    out = capsys.readouterr().out
    assert "noise.csv" in out and "left-only" in out


def test_same_seed_same_numbers_different_seed_different(tmp_path: Path) -> None:
    args = ["simulate", "translation-only", "--trials", "4", "--no-progress"]
    for name, seed, workers in (("a", "5", "1"), ("b", "5", "2"), ("c", "6", "1")):
        assert (
            main([*args, "--seed", seed, "--workers", workers, "--out", str(tmp_path / name)]) == 0
        )
    a, b, c = ((tmp_path / n / "translation-only.csv").read_text() for n in "abc")
    assert a == b
    assert a != c


@pytest.mark.parametrize("station", STATIONS, ids=lambda p: p.stem)
def test_plan_works_for_every_example_station(
    station: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["simulate", "plan", "--station", str(station), "--trials", "30", "--no-progress"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert "MEETS the recipe tolerances" in out
    assert "Cramér–Rao bound, all cameras" in out and "Monte Carlo, 30 trials" in out
    assert "worst first" in out


def test_plan_out_of_tolerance_exits_1(capsys: pytest.CaptureFixture[str]) -> None:
    lab = str(ROOT / "deploy" / "stations" / "lab.yaml")
    rc = main(
        [
            "simulate",
            "plan",
            "--station",
            lab,
            "--detector-noise",
            "3",
            "--trials",
            "10",
            "--no-progress",
        ]
    )
    assert rc == 1
    assert "DOES NOT MEET" in capsys.readouterr().out


def _undetermined_station(tmp_path: Path) -> Path:
    data = yaml.safe_load((ROOT / "deploy" / "stations" / "lab.yaml").read_text())
    rec = data["recipes"][0]
    rec["sightings"] = [s | {"marks": ["M1", "M4"]} for s in rec["sightings"] if s["view"] == 2]
    path = tmp_path / "two_marks.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["bogus"], "unknown study 'bogus'"),
        (["noise", "--trials", "0"], "--trials must be at least 1"),
        (["noise", "--station", "x.yaml"], "--station applies to 'plan' only"),
        (["plan"], "plan needs --station"),
        (["plan", "--station", "LAB", "--recipe", "nope"], "has no recipe 'nope'"),
        (
            ["plan", "--station", "LAB", "--detector-noise", "-0.5"],
            "--detector-noise must be a positive",
        ),
        (["plan", "--station", "MISSING"], "cannot read station file"),
        (["plan", "--station", "UNDETERMINED"], "pose not determined: 2 distinct marks"),
        (["plan", "--station", "LAB", "--handeye", "medium"], "unknown hand-eye level 'medium'"),
    ],
)
def test_bad_arguments_give_one_line_errors(
    args: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    paths = {
        "LAB": str(ROOT / "deploy" / "stations" / "lab.yaml"),
        "MISSING": str(tmp_path / "missing.yaml"),
        "UNDETERMINED": str(_undetermined_station(tmp_path)),
    }
    argv = ["simulate", *[paths.get(a, a) for a in args], "--no-progress", "--out", str(tmp_path)]
    rc = main(argv)
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert message in err
    assert len(err.splitlines()) == 1 and err.startswith("mvpose simulate: error:")


def test_docs_figures_come_from_the_current_studies() -> None:
    """docs/simulation.md's CSVs match today's study definitions (rerun the command if not)."""
    doc = (ROOT / "docs" / "simulation.md").read_text(encoding="utf-8")
    assert "mvpose simulate all --trials 2000 --out docs/figures" in doc
    for name in ("noise", "marks", "views", "translation-only"):
        study = get_study(name)
        rows = read_csv(ROOT / "docs" / "figures" / f"{name}.csv")
        assert {(r.series, r.x) for r in rows} == {(p.series, p.x) for p in study.points}, name
        assert all(r.trials == 2000 for r in rows)
        assert f"figures/{name}.png" in doc and (ROOT / "docs" / "figures" / f"{name}.png").exists()


def test_docs_plan_example_matches_the_command(capsys: pytest.CaptureFixture[str]) -> None:
    doc = (ROOT / "docs" / "simulation.md").read_text(encoding="utf-8")
    station2 = str(ROOT / "deploy" / "stations" / "station2.yaml")
    main(["simulate", "plan", "--station", station2, "--trials", "20", "--no-progress"])
    out = capsys.readouterr().out.splitlines()
    # the bound and the ranking are deterministic; the Monte Carlo line depends on the trials
    for line in out:
        if "Cramér–Rao" in line or "camera top " in line or line.startswith("station "):
            assert line in doc, line
