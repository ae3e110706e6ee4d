"""``mvpose demo --triggers N``: the whole server on station 1 and the PLC twin (over Modbus,
EtherNet/IP, S7 or PROFINET); REST printed."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from stations import relaxed_deadline, station_file

from server.cli import main


@pytest.mark.timeout(180)
@pytest.mark.parametrize(("link", "bus"), [("modbus", "Modbus"), ("enip", "EtherNet/IP")])
def test_demo_measures_n_triggers_and_stops(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], link: str, bus: str
) -> None:
    rc = main(["demo", "--triggers", "2", "--port", "0", "--data-dir", str(tmp_path / "var"),
               "--seed", "3", "--link", link])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert re.search(r"REST API\s+http://127\.0\.0\.1:\d+/api/v1", out)
    assert re.search(rf"^{re.escape(bus)}\s+127\.0\.0\.1:\d+", out, flags=re.M), out
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


@pytest.mark.timeout(180)
def test_demo_runs_the_line_over_s7(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--link s7``: the station polls a simulated S7 CPU's DBs (python-snap7's server)."""
    rc = main(["demo", "--link", "s7", "--triggers", "2", "--port", "0", "--data-dir",
               str(tmp_path / "var"), "--seed", "3"])
    out = capsys.readouterr().out
    assert rc == 0, out
    assert re.search(r"^S7\s+PLC 127\.0\.0\.1:\d+ .*trigger DB100, result DB101", out, re.M), out
    assert "Modbus " not in out  # the station's Modbus link is off: the PLC is on S7
    answered = re.findall(r"^\s+(?:meas\..*OK|NOK: .*)$", out, flags=re.M)
    assert len(answered) == 2, out
    assert "2 triggers:" in out


@pytest.mark.timeout(180)
@pytest.mark.skipif(os.geteuid() != 0, reason="--link profinet creates a network namespace and "
                    "a veth pair: root only (CI runs as root)")
def test_demo_runs_the_line_over_profinet_and_removes_its_namespace(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``--link profinet``: the station's IO-device on one end of a veth pair, our own
    IO-controller (the twin's port) in a namespace on the other; both gone afterwards."""
    rc = main(["demo", "--link", "profinet", "--triggers", "3", "--port", "0", "--data-dir",
               str(tmp_path / "var"), "--seed", "3"])
    out = capsys.readouterr().out
    assert rc == 0, out
    found = re.search(r"^PROFINET\s+device 'mvpose-demo' on (\S+) .* in namespace (\S+),", out,
                      re.M)
    assert found, out
    assert "Modbus " not in out  # the station's Modbus link is off: the PLC is on PROFINET
    answered = re.findall(r"^\s+(?:meas\..*OK|NOK: .*)$", out, flags=re.M)
    assert len(answered) == 3, out
    assert "3 triggers:" in out
    names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert found.group(2) not in names
    assert subprocess.run(["ip", "link", "show", found.group(1)], capture_output=True
                          ).returncode != 0


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="runs the demo as an unprivileged user: needs root and setpriv")
def test_demo_over_profinet_without_root_says_why_in_one_line(tmp_path: Path) -> None:
    env = dict(os.environ, HOME=str(tmp_path), MPLCONFIGDIR=str(tmp_path))
    done = subprocess.run(
        ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", sys.executable, "-m",
         "server.cli", "demo", "--link", "profinet", "--triggers", "1", "--data-dir",
         str(tmp_path / "var")], capture_output=True, text=True, env=env, timeout=120,
        cwd=Path(__file__).resolve().parents[2])
    assert done.returncode == 2, done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        "mvpose demo: error: --link profinet: it creates a network namespace and a veth pair, "
        "which needs root: run it as root (e.g. sudo)")


def test_demo_refuses_an_unknown_link(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["demo", "--link", "profibus", "--triggers", "1"])
    assert "invalid choice: 'profibus'" in capsys.readouterr().err


def test_demo_refuses_a_station_without_simulated_cameras(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    station = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"
    text = station.read_text().replace("kind: sim", "kind: genicam", 1)
    path = tmp_path / "real.yaml"
    path.write_text(text)
    assert main(["demo", str(path), "--triggers", "1", "--data-dir", str(tmp_path)]) == 2
    assert "needs simulated cameras" in capsys.readouterr().err


@pytest.mark.timeout(300)
def test_demo_writes_its_truth_file_and_keeps_serving_the_page_until_ctrl_c(
    tmp_path: Path,
) -> None:
    import csv
    import io
    import os
    import signal
    import subprocess
    import sys
    import time

    import httpx

    token = "mvp_demo-token-for-the-keep-serving-test"
    truth = tmp_path / "truth.csv"
    log_path = tmp_path / "demo.log"
    env = dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=token, PYTHONUNBUFFERED="1")
    # station 1 with the relaxed deadline: both triggers must be OK, and station 1's 50 ms
    # turned a loaded machine's scheduling into DEADLINE_EXCEEDED
    path = station_file(tmp_path, "station1", relaxed_deadline)
    with log_path.open("wb") as log:
        demo = subprocess.Popen(
            [sys.executable, "-m", "server.cli", "demo", str(path), "--triggers", "2",
             "--keep-serving",
             "--truth-out", str(truth), "--port", "0", "--data-dir", str(tmp_path / "var"),
             "--seed", "4"], env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            deadline = time.monotonic() + 240
            while not (found := re.search(r"still up at (http://127\.0\.0\.1:\d+)/",
                                          log_path.read_text())):
                assert demo.poll() is None, log_path.read_text()
                assert time.monotonic() < deadline, log_path.read_text()
                time.sleep(0.2)
            base = found.group(1)
            # after its triggers the demo still serves the operator page and the REST API
            assert httpx.get(f"{base}/login", timeout=30).status_code == 200
            export = httpx.get(f"{base}/api/v1/measurements/export", params={"format": "csv"},
                               headers={"Authorization": f"Bearer {token}"}, timeout=30)
            assert export.status_code == 200
        finally:
            demo.send_signal(signal.SIGINT)
            code = demo.wait(timeout=60)
    out = log_path.read_text()
    assert code == 0 and "stopped" in out, out
    rows = list(csv.DictReader(truth.open()))
    assert [r["trigger_id"] for r in rows] == ["1", "2"]
    assert [r["part_id"] for r in rows] == ["DEMO-1", "DEMO-2"]
    measured = {r["trigger_id"]: r for r in csv.DictReader(io.StringIO(export.text))}
    for r in rows:
        assert r["result"] == "OK" and float(r["trans_err_mm"]) < 1.0, r
        stored = [float(measured[r["trigger_id"]][f"o{k}"]) for k in range(1, 7)]
        mine = [float(r[f"measured_{lab}"]) for lab in ("X", "Y", "Z", "W", "P", "R")]
        assert max(abs(a - b) for a, b in zip(stored, mine, strict=True)) < 1e-3
    (tmp_path / "export.csv").write_text(export.text)
    station = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"
    assert main(["validate", "--station", str(station), "--truth", str(truth),
                 "--measured", str(tmp_path / "export.csv")]) == 0
