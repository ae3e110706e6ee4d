"""The control channel's typed round trip: every operation through a real ControlServer and a
StationClient over the Unix socket, on a real station (simulated cameras); and malformed
requests answered ``invalid``, naming what is wrong."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from stations import relaxed_deadline, runtime_options, settings_for, station_file

from mvpose_core.calibration.session import HandEyeCode
from mvpose_core.reasons import Reason
from mvpose_core.station import load_station
from server.errors import InvalidInputError, StationFailedError
from server.loopback import running_server
from server.station.client import StationClient
from server.station.control import ControlServer
from server.station.core import Station
from server.station.messages import (
    REQUESTS,
    ArmTeachAnswer,
    CameraViewAnswer,
    HandEyeAnswer,
    MovePartAnswer,
    PingAnswer,
    RecipeAnswer,
    ReloadAnswer,
    ReloadRecipesRequest,
    StationStatus,
    StatusRequest,
    TriggerAnswer,
    VerifyAnswer,
)

OPS = {"ping", "status", "readiness", "trigger", "arm_teach", "teach", "activate_recipe",
       "reload_recipes", "metrics", "move_part", "verify", "handeye", "camera_view"}


async def test_every_operation_round_trips_through_its_models(tmp_path: Path) -> None:
    assert set(REQUESTS) == OPS  # a new operation gets its round trip here
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    opts = replace(runtime_options(), sim_part_at_reference=True)
    async with running_server(settings, opts, http_port=None) as rs:
        rt = rs.runtime
        assert rt.active is not None
        recipe = rt.active.config.name
        client = StationClient(settings.resolved_control_socket, status_max_age_s=0.0)

        def run() -> None:
            ping = client.ping()
            assert isinstance(ping, PingAnswer)
            assert (ping.pid, ping.station) == (os.getpid(), "station1")

            status = client.status()
            assert isinstance(status, StationStatus) and status.station == "station1"
            assert status.recipe is not None and status.recipe.name == recipe
            assert status.links["modbus"]["port"] == rt.link_port("modbus")
            assert not status.teach_armed
            assert set(status.model_dump()) == set(rt.status())  # every part, no more

            assert client.readiness() == {"station": True, "cameras": True, "links": True,
                                          "recipe": True}

            assert "mvpose_" in client.metrics_text()  # the station's Prometheus text

            view = client.camera_view(320)  # the live camera view's frames
            assert isinstance(view, CameraViewAnswer) and view.seq >= 1
            assert [c.camera_id for c in view.cameras] == list(status.cameras)
            assert all(c.jpeg_base64 and 0 < c.width <= 320 for c in view.cameras), view.note

            moved = client.move_part([0.0] * 6)  # the part at the reference: a zero offset
            assert isinstance(moved, MovePartAnswer)
            assert (moved.recipe, moved.convention, moved.offset) == (recipe, "fanuc", [0.0] * 6)
            assert len(moved.T_rf_from_pf) == 4

            answer = client.trigger(part_id="VIN-7", view_index=0, trigger_id=7)
            assert isinstance(answer, TriggerAnswer)
            assert answer.result_code == 0 and answer.final, answer.message
            assert answer.record is not None and answer.record.trigger_id == 7
            assert answer.record.part_id == "VIN-7" and answer.offset is not None
            event = answer.event  # the result event, as every outlet shows it
            assert event is not None and event.result_id == answer.result_id
            assert (event.part_id, list(event.offset or ())) == ("VIN-7", answer.offset)
            rt.wait_idle(30)
            last = rt.last
            assert last is not None and last["result_id"] == event.result_id
            measurement_id = last["measurement_id"]
            assert measurement_id is not None

            verified = client.verify("tester")  # the part is at its reference: passed
            assert isinstance(verified, VerifyAnswer) and verified.result_code == 0
            assert verified.report is not None and verified.report.passed, verified.message
            assert verified.report.result_id == verified.result_id > event.result_id

            # station 1's cameras are fixed: a hand-eye session is refused, naming why
            he = client.handeye("begin", "tester")
            assert isinstance(he, HandEyeAnswer) and he.code == HandEyeCode.NOT_AVAILABLE
            assert "calibration_board" in he.message and not he.session["active"]
            assert client.handeye("status", "tester").code == HandEyeCode.NOT_AVAILABLE

            armed = client.arm_teach("tester")
            assert armed == ArmTeachAnswer(armed=True, recipe=recipe)
            assert client.status().teach_armed
            # a verify now would become the reference: refused, naming the teach
            refused = client.verify("tester")
            assert (refused.result_code, refused.report) == (Reason.BUSY, None)
            assert "teach" in refused.message

            before = rt.active.version if rt.active else 0
            taught = client.teach_from_measurement(measurement_id, "tester")
            assert isinstance(taught, RecipeAnswer)
            assert taught.name == recipe and taught.version > before
            assert set(taught.T_rf_from_pf0) >= {"xyz", "wpr"}

            active = client.activate_recipe(recipe, None, "tester")
            assert (active.name, active.version) == (recipe, taught.version)

            client.reload_recipes()
            assert client.ask(ReloadRecipesRequest(), ReloadAnswer) == ReloadAnswer(
                changed=False)

        await asyncio.to_thread(run)


def _exchange(path: Path, line: bytes) -> dict[str, Any]:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(10.0)
        sock.connect(str(path))
        sock.sendall(line)
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    answer: dict[str, Any] = json.loads(data)
    return answer


@pytest.mark.parametrize(("request_", "words"), [
    ({"op": "teach", "args": {"measurement_id": "5", "by": "x"}},
     ["teach", "'measurement_id'", "integer"]),
    ({"op": "arm_teach", "args": {}}, ["arm_teach", "'by'", "required"]),
    ({"op": "arm_teach", "args": {"by": ""}}, ["'by'", "at least 1"]),
    ({"op": "trigger", "args": {"view": 0, "colour": "red"}}, ["trigger", "'colour'"]),
    ({"op": "trigger", "args": {"view": 256}}, ["'view'", "255"]),
    ({"op": "activate_recipe", "args": {"name": "p", "version": True, "by": "x"}},
     ["'version'", "integer"]),
    ({"op": "move_part", "args": {"offset": [0, "1"]}}, ["move_part", "'offset.1'", "number"]),
    ({"op": "fly", "args": {}}, ["unknown control operation 'fly'"]),
])
async def test_a_malformed_request_is_answered_invalid_naming_the_argument(
    tmp_path: Path, request_: dict[str, Any], words: list[str],
) -> None:
    # Validation comes before the station is asked: a station that is not started answers it.
    station = Station(load_station(station_file(tmp_path, "station1")))
    server = ControlServer(station, tmp_path / "station.sock")
    await server.start()
    try:
        answer = await asyncio.to_thread(
            _exchange, server.path, json.dumps({"id": 3, **request_}).encode() + b"\n")
        assert answer["id"] == 3 and answer["ok"] is False
        assert answer["error"]["kind"] == "invalid"
        for word in words:
            assert word in answer["error"]["message"], answer
    finally:
        await server.stop()


async def test_the_client_maps_invalid_and_refuses_a_wrong_answer_model(tmp_path: Path) -> None:
    station = Station(load_station(station_file(tmp_path, "station1")))
    server = ControlServer(station, tmp_path / "station.sock")
    await server.start()
    try:
        client = StationClient(server.path)
        with pytest.raises(InvalidInputError, match="'measurement_id'"):
            await asyncio.to_thread(client.call, "teach", measurement_id="5", by="x")
        with pytest.raises(InvalidInputError, match="'by'"):  # refused before it is sent
            await asyncio.to_thread(client.arm_teach, "")
        with pytest.raises(TypeError, match="StationStatus"):
            client.ask(StatusRequest(), PingAnswer)
        answer = await asyncio.to_thread(
            _exchange, server.path, b"not json\n")
        assert answer["ok"] is False and answer["error"] == {
            "kind": "invalid", "message": "not a control request"}
    finally:
        await server.stop()


def test_a_failure_inside_the_station_is_a_gateway_error_not_a_bug_of_the_api(
        tmp_path: Path) -> None:
    """A station that answers 'internal' (an exception in its own code) reaches the API as
    StationFailedError (502 problem), never as an unhandled exception (a 500)."""
    path = tmp_path / "control.sock"
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(str(path))
    listener.listen(1)

    def answer_once() -> None:  # the wire's other end, as a failing station writes it
        conn, _ = listener.accept()
        with conn:
            request = json.loads(conn.makefile().readline())
            conn.sendall(json.dumps({"id": request["id"], "ok": False, "error": {
                "kind": "internal", "message": "KeyError: 'x'"}}).encode() + b"\n")

    server = threading.Thread(target=answer_once, daemon=True)
    server.start()
    try:
        with pytest.raises(StationFailedError, match="the station failed: KeyError") as info:
            StationClient(path, timeout_s=10).call("ping")
        assert info.value.status == 502
    finally:
        server.join(10)
        listener.close()
