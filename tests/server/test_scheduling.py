"""The station process's trigger path under the real-time FIFO policy (server.station.scheduling).

`mvpose station` is started as it is deployed (its own process, the command line); the threads
are looked up in /proc. The thread that did the triggers' work (the one with the most CPU time
after a few triggers: detection, estimation) must run at the configured priority; with priority 0
every thread runs under the normal scheduler and the status says why.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from stations import relaxed_deadline, station_file

from server.station.client import StationClient, StationDownError

START_S = 90.0


def _start(tmp_path: Path, *extra: str, env: dict[str, str] | None = None,
           edit: Any = None) -> tuple[subprocess.Popen[bytes], StationClient]:
    path = station_file(tmp_path, "station1", relaxed_deadline, *([edit] if edit else []))
    data = tmp_path / "var"
    log = (tmp_path / "station.log").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "station", "--station", str(path), "--data-dir",
         str(data), "--plc-port", "0", "--log-level", "warning", *extra],
        stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, **(env or {})))
    client = StationClient(data / "station.sock")
    deadline = time.monotonic() + START_S
    while True:
        assert proc.poll() is None, (tmp_path / "station.log").read_text()[-2000:]
        try:
            client.call("ping", timeout_s=1.0)
            return proc, client
        except StationDownError:
            assert time.monotonic() < deadline, "the station process did not answer"
            time.sleep(0.1)


def _threads(pid: int) -> list[dict[str, Any]]:
    """Each task of ``pid``: its id, policy, real-time priority and CPU ticks so far."""
    out = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        tid = int(task.name)
        fields = (task / "stat").read_text().rsplit(")", 1)[1].split()
        out.append({"tid": tid, "policy": os.sched_getscheduler(tid),
                    "priority": os.sched_getparam(tid).sched_priority,
                    "ticks": int(fields[11]) + int(fields[12])})  # utime + stime
    return out


def _stop(proc: subprocess.Popen[bytes]) -> None:
    proc.terminate()
    assert proc.wait(timeout=30) == 0


def test_the_trigger_path_runs_under_the_fifo_policy(tmp_path: Path) -> None:
    proc, client = _start(tmp_path, "--trigger-priority", "12")
    try:
        assert client.status().part("cpu") == {"policy": "fifo", "priority": 12}
        for k in range(8):
            assert client.trigger(trigger_id=k + 1).result_code == 0
        busiest = max(_threads(proc.pid), key=lambda t: t["ticks"])
        assert busiest["ticks"] > 0
        assert (busiest["policy"], busiest["priority"]) == (os.SCHED_FIFO, 12), busiest
    finally:
        _stop(proc)


def test_priority_zero_keeps_the_normal_scheduler_and_says_so(tmp_path: Path) -> None:
    # the environment variable, as a container sets it
    proc, client = _start(tmp_path, env={"MVPOSE_TRIGGER_PRIORITY": "0"})
    try:
        cpu = client.status().part("cpu")
        assert cpu["policy"] == "normal" and "off" in cpu["why"]
        assert {t["policy"] for t in _threads(proc.pid)} == {os.SCHED_OTHER}
    finally:
        _stop(proc)


def test_the_opcua_link_process_runs_normal_and_ends_with_the_station(tmp_path: Path) -> None:
    """The OPC UA server's process (drivers.links.process) is the station's child under the
    normal scheduler, whatever the trigger path runs under; SIGTERM ends both."""

    def opcua(data: dict[str, Any]) -> None:
        data.setdefault("links", {})["opcua"] = {"port": 0, "security": ["None"],
                                                 "allow_anonymous": True}

    proc, client = _start(tmp_path, "--trigger-priority", "12", edit=opcua)
    try:
        deadline = time.monotonic() + START_S
        while not (link := client.status().links["opcua"]).get("running"):
            assert time.monotonic() < deadline, link
            time.sleep(0.1)
        child = link["pid"]
        assert int((Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split())[1]) \
            == proc.pid
        assert {t["policy"] for t in _threads(child)} == {os.SCHED_OTHER}
        assert client.status().part("cpu") == {"policy": "fifo", "priority": 12}
    finally:
        t = time.monotonic()
        _stop(proc)
    assert time.monotonic() - t < 5.0  # what a container runtime waits after SIGTERM
    assert not Path(f"/proc/{child}").exists()


def test_the_modbus_link_process_runs_at_the_trigger_priority(tmp_path: Path) -> None:
    """The Modbus link's process (drivers.links.REALTIME) is the station's child at the trigger
    path's FIFO priority: the PLC's polls and its handshake do not wait for normal tasks. It
    ends with the station."""
    proc, client = _start(tmp_path, "--trigger-priority", "12")
    try:
        deadline = time.monotonic() + START_S
        while not (link := client.status().links["modbus"]).get("running"):
            assert time.monotonic() < deadline, link
            time.sleep(0.1)
        child = link["pid"]
        assert int((Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split())[1]) \
            == proc.pid
        assert {(t["policy"], t["priority"]) for t in _threads(child)} == {(os.SCHED_FIFO, 12)}
    finally:
        _stop(proc)
    assert not Path(f"/proc/{child}").exists()


@pytest.mark.parametrize("value", ["100", "-1", "high"])
def test_a_bad_priority_is_a_one_line_start_up_error(tmp_path: Path, value: str) -> None:
    path = station_file(tmp_path, "station1", relaxed_deadline)
    done = subprocess.run(
        [sys.executable, "-m", "server.cli", "station", "--station", str(path), "--data-dir",
         str(tmp_path / "var"), "--plc-port", "0", "--trigger-priority", value],
        capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "trigger-priority" in done.stderr or "TRIGGER_PRIORITY" in done.stderr, done.stderr
    assert "Traceback" not in done.stderr


def _in_thread(start_fifo: bool) -> dict[str, Any]:
    """beneath() in a new thread (real-time at 10 first when ``start_fifo``): its policy after."""
    import threading

    from server.station import scheduling

    out: dict[str, Any] = {}

    def run() -> None:
        if start_fifo:
            try:
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
            except OSError as err:
                out["refused"] = str(err)
                return
        scheduling.beneath()
        out.update(policy=os.sched_getscheduler(0), priority=os.sched_getparam(0).sched_priority,
                   nice=os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))

    t = threading.Thread(target=run)
    t.start()
    t.join(10)
    return out


def test_beneath_keeps_a_thread_real_time_below_the_trigger_path() -> None:
    out = _in_thread(start_fifo=True)
    if "refused" in out:
        pytest.skip(f"no real-time policy on this machine: {out['refused']}")
    assert (out["policy"], out["priority"]) == (os.SCHED_FIFO, 1)
    # a station without the real-time policy: the thread is niced, as background() does
    out = _in_thread(start_fifo=False)
    assert out["policy"] == os.SCHED_OTHER and out["nice"] >= 10
