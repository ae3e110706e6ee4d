"""Alarms from a real station process to Debian's Mosquitto: its Modbus link without a PLC
raises LINK_NO_PLC (after the on-delay), an operator's acknowledgement written by another
process (the API's) and the clearing when a PLC connects each reach an independent subscriber
on ``.../mvpose/alarms``, once per transition after deduplication by ``event_id``."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from mqtt_broker import Mosquitto, Subscriber
from stations import relaxed_deadline, station_file
from test_mqtt import PLANT, START_S, _plant, _ready, _station
from waiting import until

from server.loopback import attach_twin, detach_twin
from server.station.client import StationClient
from server.store import open_store

TOPIC = "acme/wob/body/l3/station1/mvpose/alarms"


def _events(sub: Subscriber) -> dict[int, dict[str, Any]]:
    out: dict[int, dict[str, Any]] = {}
    for p in sub.on("/mvpose/alarms"):
        assert out.setdefault(p["event_id"], p) == p, f"two messages for event {p['event_id']}"
    return out


def _of(sub: Subscriber, code: str) -> list[tuple[str, str | None]]:
    return [(p["event"], p["by"]) for _, p in sorted(_events(sub).items())
            if p["alarm"]["code"] == code]


async def test_link_alarm_raised_acknowledged_and_cleared_over_mqtt(tmp_path: Path) -> None:
    broker = Mosquitto(tmp_path)
    broker.start()
    sub = Subscriber(broker.port, [f"{'/'.join(PLANT.values())}/+/mvpose/#"])
    path = station_file(tmp_path, "station1", relaxed_deadline, _plant(broker.port))
    data = tmp_path / "var"
    log = tmp_path / "station.log"
    client = StationClient(data / "station.sock")
    proc = _station(path, data, log)
    try:
        await until(lambda: _ready(client, proc, log), "the station process answers", START_S)
        await until(lambda: _of(sub, "LINK_NO_PLC") == [("raised", None)],
                    "LINK_NO_PLC raised on MQTT", 30)
        raised = next(p for p in _events(sub).values() if p["alarm"]["code"] == "LINK_NO_PLC")
        assert raised["schema"] == "mvpose.alarm/1"
        assert raised["alarm"] | {"id": 0, "raised_at": ""} == {
            "id": 0, "station": "station1", "source": "link:modbus", "code": "LINK_NO_PLC",
            "priority": "high", "text": "link modbus: no PLC heartbeat",
            "text_key": "alarm.LINK_NO_PLC", "text_args": {"link": "modbus"}, "raised_at": "",
            "cleared_at": None, "acked_at": None, "acked_by": None, "active": True,
            "acknowledged": False}

        # acknowledged from another process on the same database (the API's): published by
        # the station's publisher from the outbox
        store = open_store(f"sqlite:///{data / 'mvpose.db'}", "station1")
        store.alarms.topic = TOPIC
        try:
            store.alarms.acknowledge(raised["alarm"]["id"], "alice")
        finally:
            store.close()
        await until(lambda: ("acknowledged", "alice") in _of(sub, "LINK_NO_PLC"),
                    "the acknowledgement on MQTT", 30)

        # a PLC connects: the link leaves PREOPERATIONAL and the alarm clears
        port = (await asyncio.to_thread(client.status)).links["modbus"]["port"]
        twin, beat = await attach_twin(port, poll_s=0.01)
        try:
            await until(lambda: _of(sub, "LINK_NO_PLC")[-1:] == [("cleared", None)],
                        "LINK_NO_PLC cleared on MQTT", 30)
        finally:
            await detach_twin(twin, beat)
        assert _of(sub, "LINK_NO_PLC") == [("raised", None), ("acknowledged", "alice"),
                                           ("cleared", None)]
        last = max(_events(sub).values(), key=lambda p: p["event_id"] if
                   p["alarm"]["code"] == "LINK_NO_PLC" else 0)
        assert last["alarm"]["acked_by"] == "alice" and not last["alarm"]["active"]
        status = (await asyncio.to_thread(client.status)).part("alarms")
        assert status["last_error"] is None
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        sub.close()
        broker.stop()
