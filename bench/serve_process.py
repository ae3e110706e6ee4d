"""`mvpose serve` started as it is deployed, for the benchmarks: its own processes, found by port.

The supervisor, the station process and the API process run exactly as in production (``python
-m server.cli serve``), with the Modbus link and the REST API on free loopback ports (port 0):
the station's status (control channel) says the Modbus port, ``<data_dir>/api.json`` the REST
port. The benchmark then talks to them only from outside: the PLC twin over Modbus/TCP, the MES
over HTTP, the RSS of the station process through /proc.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from dataclasses import dataclass
from pathlib import Path

from server.station.client import StationClient, StationDownError

ROOT = Path(__file__).resolve().parents[1]
TOKEN = "mvp_bench-station-token-0000000000000000000000"


@dataclass
class Serve:
    """A running `mvpose serve` and what the benchmark needs to reach it."""

    proc: subprocess.Popen[bytes]
    station: str  # the station's name (the store keeps records per station)
    data_dir: Path
    plc_port: int
    base_url: str
    station_pid: int
    api_pid: int
    ready_s: float  # from the command's start to both processes serving
    log: Path

    @property
    def client(self) -> StationClient:
        return StationClient(self.data_dir / "station.sock", timeout_s=5.0)

    def status(self) -> dict:
        return self.client.status().model_dump(mode="json")

    def stop(self, timeout_s: float = 20.0) -> float:
        """SIGTERM the supervisor; the seconds until it exited (killed after ``timeout_s``)."""
        if self.proc.poll() is not None:
            return 0.0
        t = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        return time.monotonic() - t


def start_serve(station_file: Path, station: str, data_dir: Path, *,
                extra_env: dict[str, str] | None = None, timeout_s: float = 300.0) -> Serve:
    """Start `mvpose serve` on ``station_file`` and wait until both processes serve."""
    env = dict(os.environ)
    env.update({"MVPOSE_BOOTSTRAP_TOKEN": TOKEN, "PYTHONUNBUFFERED": "1"})
    env.update(extra_env or {})
    data_dir.mkdir(parents=True, exist_ok=True)
    log = data_dir / "serve.log"
    t0 = time.monotonic()
    with log.open("wb") as out:
        proc = subprocess.Popen(  # noqa: S603 - our own interpreter and module
            [sys.executable, "-m", "server.cli", "serve", "--station", str(station_file),
             "--data-dir", str(data_dir), "--host", "127.0.0.1", "--port", "0",
             "--plc-host", "127.0.0.1", "--plc-port", "0", "--log-level", "warning"],
            cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    client = StationClient(data_dir / "station.sock", timeout_s=2.0)
    address = data_dir / "api.json"
    deadline = time.monotonic() + timeout_s
    status = None
    base_url = ""
    api_pid = 0
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"mvpose serve exited with {proc.returncode}: "
                               f"{log.read_text(errors='replace')[-3000:]}")
        if status is None:
            with contextlib.suppress(StationDownError):
                status = client.status().model_dump(mode="json")
        if not base_url:
            try:
                info = json.loads(address.read_text())
                url = f"http://127.0.0.1:{info['port']}"
                with urllib.request.urlopen(url + "/api/v1/health/live", timeout=1.0):
                    base_url, api_pid = url, int(info["pid"])
            except (OSError, ValueError, KeyError):
                pass
        if status is not None and base_url:
            break
        time.sleep(0.1)
    else:
        proc.kill()
        raise TimeoutError(f"mvpose serve was not ready within {timeout_s:.0f} s: "
                           f"{log.read_text(errors='replace')[-3000:]}")
    assert status is not None
    return Serve(proc=proc, station=station, data_dir=data_dir,
                 plc_port=int(status["links"]["modbus"]["port"]), base_url=base_url,
                 station_pid=int(status["pid"]), api_pid=api_pid,
                 ready_s=time.monotonic() - t0, log=log)


def rss_kb(pid: int) -> int:
    """Resident set size of a process (Linux /proc), KiB; 0 when unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return 0


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a running process (Linux /proc; 0 elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0
