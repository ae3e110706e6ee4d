"""`mvpose serve` as it runs on a station: two processes, each killed with SIGKILL and restarted.

The supervisor, the station process and the API process are real processes started by the
command line; the PLC is the twin in this test's process, talking Modbus/TCP (or EtherNet/IP
class 1 I/O) on loopback. While the twin triggers back to back, the API process is killed: no
trigger fails. Then the station
process is killed: the API keeps serving history and its readiness says the station is down,
until the station is back; result ids go on from where they were, never reused.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest
from stations import ENGINEER, relaxed_deadline, station_file

from server.loopback import attach_twin, detach_twin
from server.station.client import StationClient, StationDownError
from tests.drivers import profinet_peer

START_S = 120.0  # two processes, migrations and four simulated 4 MP cameras on a loaded machine


def _ping(client: StationClient) -> dict[str, Any] | None:
    try:
        result: dict[str, Any] = client.call("ping", timeout_s=1.0)
        return result
    except StationDownError:
        return None


async def _until(what: str, check: Any, timeout: float = START_S) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        got = await asyncio.to_thread(check)
        if got:
            return got
        assert time.monotonic() < deadline, f"{what} within {timeout:g} s"
        await asyncio.sleep(0.1)


def _api(data_dir: Path) -> dict[str, Any] | None:
    try:
        found: dict[str, Any] = json.loads((data_dir / "api.json").read_text())
    except (OSError, ValueError):
        return None
    try:
        live = httpx.get(f"http://127.0.0.1:{found['port']}/api/v1/health/live", timeout=1.0)
    except httpx.HTTPError:
        return None
    return found if live.status_code == 200 else None


def _enip(data: dict[str, Any]) -> None:
    data["links"]["enip"] = {"port": 0, "io_port": 0, "watchdog_s": 10.0}


@pytest.mark.parametrize("link", ["modbus", "enip"])
async def test_serve_keeps_triggering_through_kills_of_either_process(tmp_path: Path,
                                                                      link: str) -> None:
    path = station_file(tmp_path, "station1", relaxed_deadline,
                        *((_enip,) if link == "enip" else ()))
    data = tmp_path / "var"
    env = dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=ENGINEER)
    log = (tmp_path / "serve.log").open("wb")
    serve = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "serve", "--station", str(path), "--data-dir",
         str(data), "--port", "0", "--plc-port", "0", "--log-level", "warning"],
        env=env, stdout=log, stderr=subprocess.STDOUT)
    client = StationClient(data / "station.sock")
    try:
        station = await _until("the station process answers", lambda: _ping(client))
        api = await _until("the API process answers", lambda: _api(data))
        port = (await asyncio.to_thread(client.status)).links[link]["port"]
        twin, beat = await attach_twin(port, poll_s=0.002, link=link)
        answers: list[tuple[int, int, int]] = []
        try:
            async def storm(first: int, n: int) -> None:
                for k in range(first, first + n):
                    status = await twin.cycle(k, timeout=10.0)
                    answers.append((k, status.result_code, status.result_id))

            run = asyncio.create_task(storm(1, 30))
            await _until("a few triggers answered", lambda: len(answers) >= 5, 60)
            os.kill(api["pid"], signal.SIGKILL)
            await run
            assert [code for _, code, _ in answers] == [0] * 30, answers
            back = await _until("a new API process",
                                lambda: (a := _api(data)) and a["pid"] != api["pid"] and a)
            api = back
        finally:
            await detach_twin(twin, beat)

        base = f"http://127.0.0.1:{api['port']}/api/v1"
        auth = {"Authorization": f"Bearer {ENGINEER}"}
        async with httpx.AsyncClient(base_url=base, headers=auth, timeout=10) as http:
            os.kill(station["pid"], signal.SIGKILL)

            async def down() -> bool:
                r = await http.get("/health/ready")
                return r.status_code == 503 and r.json()["checks"].get("station") is False

            deadline = time.monotonic() + 10
            while not await down():
                assert time.monotonic() < deadline, "readiness never said the station is down"
                await asyncio.sleep(0.05)
            history = await http.get("/measurements", params={"limit": 100})
            assert history.status_code == 200
            assert len(history.json()["items"]) == 30  # history is served while it is down
            assert (await http.get("/station/status")).status_code == 503

            restarted = await _until(
                "a new station process",
                lambda: (p := _ping(client)) and p["pid"] != station["pid"] and p)
            assert restarted["pid"] != station["pid"]
            port = (await asyncio.to_thread(client.status)).links[link]["port"]
            twin, beat = await attach_twin(port, poll_s=0.002, link=link)
            try:
                for k in range(31, 34):
                    status = await twin.cycle(k, timeout=10.0)
                    answers.append((k, status.result_code, status.result_id))
            finally:
                await detach_twin(twin, beat)
            ids = [rid for _, _, rid in answers]
            assert ids == sorted(set(ids)), f"result ids reused after the restart: {ids}"
            await _until("the API is ready again",
                         lambda: httpx.get(base + "/health/ready", timeout=2).status_code == 200,
                         30)
            for k, code, rid in answers[-3:]:
                found = (await http.get("/measurements", params={"result_id": rid})).json()
                assert [(m["trigger_id"], m["reason_code"]) for m in found["items"]] == [
                    (k, code)]
            # the supervisor raised STATION_DOWN when the process died, cleared it when ready
            # (written on a thread of its own: waited for)
            deadline = time.monotonic() + 10
            while True:
                down = (await http.get("/alarms", params={"source": "station"})).json()["items"]
                if [a["active"] for a in down] == [False]:
                    break
                assert time.monotonic() < deadline, f"STATION_DOWN not cleared: {down}"
                await asyncio.sleep(0.05)
            assert [(a["code"], a["text_args"]["exit_code"]) for a in down] == [
                ("STATION_DOWN", -signal.SIGKILL)], down
    finally:
        t = time.monotonic()
        serve.send_signal(signal.SIGTERM)
        code = serve.wait(timeout=30)
        stopped_s = time.monotonic() - t
        log.close()
    assert code == 0, (tmp_path / "serve.log").read_text()[-3000:]
    assert stopped_s < 5.0, f"SIGTERM took {stopped_s:.1f} s"
    assert not (data / "station.sock").exists()


@pytest.mark.skipif(profinet_peer.usable() is not None, reason=str(profinet_peer.usable()))
async def test_serve_keeps_its_result_ids_through_a_kill_of_the_station_over_profinet(
        tmp_path: Path) -> None:
    """The PLC durability rule over PROFINET: profinet-py the IO-controller on a veth pair;
    the station process killed with SIGKILL between triggers takes the device (its child) with
    it; the controller connects again to the restarted one. 0 lost, 0 doubled, 0 reused ids."""
    name = "mvpose-station"
    with profinet_peer.veth(5) as net:
        def profinet(data: dict[str, Any]) -> None:
            data["links"]["profinet"] = {"interface": net.device_if, "station_name": name,
                                         "rpc_host": net.device_ip, "watchdog_s": 10.0}

        path = station_file(tmp_path, "station1", relaxed_deadline, profinet)
        data = tmp_path / "var"
        env = dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=ENGINEER)
        log = (tmp_path / "serve.log").open("wb")
        serve = subprocess.Popen(
            [sys.executable, "-m", "server.cli", "serve", "--station", str(path), "--data-dir",
             str(data), "--port", "0", "--plc-port", "0", "--log-level", "warning"],
            env=env, stdout=log, stderr=subprocess.STDOUT)
        client = StationClient(data / "station.sock")
        answers: list[tuple[int, int, int]] = []

        def running() -> bool:
            try:
                return bool(client.status().links["profinet"]["running"])
            except (StationDownError, KeyError):
                return False

        async def run(ctl: profinet_peer.Controller, first: int, n: int) -> None:
            async with profinet_peer.plc(ctl, ready=True) as twin:
                for k in range(first, first + n):
                    status = await twin.cycle(k, timeout=10.0)
                    answers.append((k, status.result_code, status.result_id))

        try:
            station = await _until("the station process answers", lambda: _ping(client))
            await _until("the PROFINET link running", running)
            async with profinet_peer.controller(net) as ctl:
                await ctl.run_ar(name, reduction_ratio=4)
                await run(ctl, 1, 10)
                os.kill(station["pid"], signal.SIGKILL)
                await ctl.ok("stop_cyclic")  # the AR went with the device
                await _until("a new station process",
                             lambda: (p := _ping(client)) and p["pid"] != station["pid"] and p)
                await _until("the PROFINET link running again", running)
                await ctl.run_ar(name, reduction_ratio=4)
                await run(ctl, 11, 3)
            assert [code for _, code, _ in answers] == [0] * 13, answers
            ids = [rid for _, _, rid in answers]
            assert ids == sorted(set(ids)), f"result ids doubled or reused: {ids}"
            api = await _until("the API process answers", lambda: _api(data))
            base = f"http://127.0.0.1:{api['port']}/api/v1"
            auth = {"Authorization": f"Bearer {ENGINEER}"}
            async with httpx.AsyncClient(base_url=base, headers=auth, timeout=10) as http:
                for k, code, rid in answers:
                    found = (await http.get("/measurements", params={"result_id": rid})).json()
                    assert [(m["trigger_id"], m["reason_code"]) for m in found["items"]] == [
                        (k, code)]
        finally:
            serve.send_signal(signal.SIGTERM)
            code = serve.wait(timeout=30)
            log.close()
        assert code == 0, (tmp_path / "serve.log").read_text()[-3000:]


def _samples(text: str, name: str) -> list[tuple[dict[str, str], float]]:
    from prometheus_client.parser import text_string_to_metric_families

    return [(s.labels, s.value) for f in text_string_to_metric_families(text)
            for s in f.samples if s.name == name]


async def test_serve_measures_two_views_rehearses_and_scrapes_the_stations_metrics(
    tmp_path: Path,
) -> None:
    """lab.yaml under `mvpose serve`: a trigger per view through REST gives OK (each view's
    capture shows that view), the engineer moves the simulated part between parts (rehearsal),
    and the API process's scrape has the station process's counters and histograms."""
    import numpy as np

    from mvpose_core.station import load_station
    from server.loopback import offset_error

    path = station_file(tmp_path, "lab", relaxed_deadline)
    recipe = load_station(path).recipe()
    data = tmp_path / "var"
    env = dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=ENGINEER)
    log = (tmp_path / "serve.log").open("wb")
    serve = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "serve", "--station", str(path), "--data-dir",
         str(data), "--port", "0", "--plc-port", "0", "--log-level", "warning"],
        env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        await _until("the station process answers", lambda: _ping(StationClient(
            data / "station.sock")))
        api = await _until("the API process answers", lambda: _api(data))
        base = f"http://127.0.0.1:{api['port']}/api/v1"
        async with httpx.AsyncClient(base_url=base, timeout=60,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as http:
            r = await http.post("/tokens", json={"name": "op", "role": "operator"})
            operator = {"Authorization": f"Bearer {r.json()['token']}"}
            r = await http.post("/station/rehearsal/part", json={"offset": [0.0] * 6},
                                headers=operator)
            assert r.status_code == 403 and "'engineer'" in r.json()["detail"]
            r = await http.post("/station/rehearsal/part", json={"offset": [1.0] * 3})
            assert r.status_code == 422, r.text

            for n, offset in enumerate(([0.0] * 6, [6.0, -4.0, 3.0, 0.4, -0.3, 0.6])):
                r = await http.post("/station/rehearsal/part", json={"offset": offset})
                assert r.status_code == 200, r.text
                assert r.json()["convention"] == recipe.robot_convention.value
                first = await http.post("/station/trigger", json={"part_id": f"P{n}", "view": 1})
                assert first.status_code == 200, first.text
                assert not first.json()["final"], first.json()
                last = (await http.post("/station/trigger",
                                        json={"part_id": f"P{n}", "view": 2})).json()
                assert last["final"] and last["reason"] == "OK", (last["reason"],
                                                                  last["message"])
                deg, mm = offset_error(recipe, np.array(offset), np.array(last["offset"]))
                assert deg <= recipe.tolerances.rotation_deg
                assert mm <= recipe.tolerances.translation_mm

            text = (await http.get("/metrics")).text
        ok = [v for labels, v in _samples(text, "mvpose_measurements_total")
              if labels["result"] == "OK"]
        assert ok == [2.0], text
        counts = {labels["stage"]: v for labels, v in
                  _samples(text, "mvpose_stage_duration_seconds_count")}
        assert counts and all(v >= 2 for v in counts.values()), counts
        buckets = _samples(text, "mvpose_stage_duration_seconds_bucket")
        assert {labels["le"] for labels, _ in buckets} >= {"0.05", "+Inf"}
        assert _samples(text, "mvpose_chain_head_seq")[0][1] >= 2
        assert _samples(text, "mvpose_station_up") == [({}, 1.0)]
    finally:
        serve.send_signal(signal.SIGTERM)
        code = serve.wait(timeout=30)
        log.close()
    assert code == 0, (tmp_path / "serve.log").read_text()[-3000:]
