"""The station over S7 when its process is killed, as the Modbus link has it (test_processes.py):
`mvpose serve`'s station process killed with SIGKILL while the line runs loses, doubles and
reuses no result id. (The frozen database runs over S7 in test_station_answers.py.)

The PLC is python-snap7's server (:class:`drivers.links.s7.twin.S7Cpu`) in this test's process,
its program the project's twin on its DBs; the station's S7 link is the client that polls it,
and connects to it again when the station comes back.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

from stations import ENGINEER, relaxed_deadline, station_file
from test_processes import START_S, _ping, _until

from drivers.links.layout import Status
from drivers.links.s7.twin import S7Cpu, S7Port
from server.loopback import attach_twin, detach_twin
from server.station.client import StationClient, StationDownError

WATCHDOG = {"watchdog_s": 10.0}  # the tests' PLC watchdog (tests/server/stations.py)


def _s7_status(client: StationClient) -> dict[str, Any]:
    try:
        found: dict[str, Any] = client.status().links["s7"]
        return found
    except StationDownError:
        return {}


def _s7_link(cpu: S7Cpu) -> Any:
    def edit(data: dict[str, Any]) -> None:
        links = data.setdefault("links", {})
        links["s7"] = {**cpu.settings, **WATCHDOG}
        links["modbus"] = {"enabled": False}  # the station's PLC state is the S7 handshake's
    return edit


async def test_serve_over_s7_loses_nothing_when_the_station_is_killed(tmp_path: Path) -> None:
    with S7Cpu() as cpu:
        path = station_file(tmp_path, "station1", relaxed_deadline, _s7_link(cpu))
        data = tmp_path / "var"
        log = (tmp_path / "serve.log").open("wb")
        serve = subprocess.Popen(
            [sys.executable, "-m", "server.cli", "serve", "--station", str(path), "--data-dir",
             str(data), "--port", "0", "--log-level", "warning"],
            env=dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=ENGINEER), stdout=log,
            stderr=subprocess.STDOUT)
        client = StationClient(data / "station.sock")
        answers: list[tuple[int, int, int]] = []
        try:
            station = await _until("the station process answers", lambda: _ping(client))
            twin, beat = await attach_twin(S7Port(cpu), 0.002)
            try:
                for k in range(1, 11):
                    status = await twin.cycle(k, timeout=10.0)
                    answers.append((k, status.result_code, status.result_id))
                os.kill(station["pid"], signal.SIGKILL)  # the line goes on triggering
                restarted = await _until(
                    "a new station process",
                    lambda: (p := _ping(client)) and p["pid"] != station["pid"] and p)
                assert restarted["pid"] != station["pid"]
                # the new process's S7 link connects to the same PLC and writes its whole
                # result block; the PLC program resets an error if it finds one, as after any
                # restart of the station
                await _until("the new station's S7 link connected",
                             lambda: _s7_status(client).get("connects", 0) >= 1)
                status = await twin.wait_for(lambda s: s.has(Status.READY | Status.ERROR),
                                             START_S, "the new station READY")
                if status.has(Status.ERROR):
                    await twin.reset_error(10.0)
                for k in range(11, 16):
                    status = await twin.cycle(k, timeout=10.0)
                    answers.append((k, status.result_code, status.result_id))
            finally:
                await detach_twin(twin, beat)
            assert [code for _, code, _ in answers] == [0] * 15, answers
            ids = [rid for _, _, rid in answers]
            assert ids == list(range(ids[0], ids[0] + 15)), f"lost, doubled or reused: {ids}"
            # the station shows the last answer's id (its status is cached for a moment)
            await _until("the S7 link's status showing the last result id",
                         lambda: _s7_status(client).get("result_id") == ids[-1], 10)
        finally:
            serve.send_signal(signal.SIGTERM)
            code = serve.wait(timeout=30)
            log.close()
        assert code == 0, (tmp_path / "serve.log").read_text()[-3000:]
