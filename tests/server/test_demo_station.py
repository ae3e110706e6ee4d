"""``mvpose demo --triggers N``: the whole server on station 1 and the PLC twin; REST printed."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from server.cli import main


@pytest.mark.timeout(180)
def test_demo_measures_n_triggers_and_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(["demo", "--triggers", "2", "--port", "0", "--data-dir", str(tmp_path / "var"),
               "--seed", "3"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert re.search(r"REST API\s+http://127\.0\.0\.1:\d+/api/v1", out)
    true_rows = re.findall(r"^\s+\d+\s+true\s", out, flags=re.M)
    assert len(true_rows) == 2
    # Each trigger is answered: measured (with its error and latency) or NOK with the reason.
    num = r"-?\d+\.\d+"
    measured = re.findall(rf"^\s+meas\.(?:\s+{num}){{3}} \|(?:\s+{num}){{3}}\s+({num})\s+({num})"
                          rf"\s+{num}\s+{num}\s+({num})\s+OK$", out, flags=re.M)
    refused = re.findall(r"^\s+NOK: .+ \(([A-Z_]+), code \d+\) after [\d.]+ ms$", out, flags=re.M)
    assert len(measured) + len(refused) == 2, out
    for rot_deg, trans_mm, server_ms in measured:
        assert float(rot_deg) < 0.2 and float(trans_mm) < 1.0 and float(server_ms) > 0.0
    assert "2 triggers:" in out
    assert (tmp_path / "var" / "mvpose.db").exists()


def test_demo_refuses_a_station_without_simulated_cameras(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    station = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"
    text = station.read_text().replace("kind: sim", "kind: genicam", 1)
    path = tmp_path / "real.yaml"
    path.write_text(text)
    assert main(["demo", str(path), "--triggers", "1", "--data-dir", str(tmp_path)]) == 2
    assert "needs simulated cameras" in capsys.readouterr().err
