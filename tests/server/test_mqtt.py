"""Results streamed through MQTT: a real station process, Debian's Mosquitto, an independent
subscriber (paho-mqtt in this process).

One station process (``python -m server.cli station``, simulated cameras, SQLite) publishes to
a broker on loopback. The test triggers it through its control channel and shows: every record
reaches the subscriber exactly once after deduplication by id, with the record's id, result id
and chain hash; the broker killed mid-run and restarted loses nothing (the triggers go on
meanwhile, answered as usual); the station stopped with unpublished rows publishes them after
its restart; the retained state says online with the recipe, and the last will says offline
when the station is killed with SIGKILL.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from mqtt_broker import Mosquitto, Subscriber, wait_until
from sqlalchemy import create_engine, text
from stations import ENGINEER, relaxed_deadline, station_file

from drivers.links.result import ResultEvent
from server.station.client import StationClient, StationDownError
from server.station.messages import TriggerAnswer

START_S = 120.0  # migrations, four simulated 4 MP cameras and their warm-up on a loaded machine
PLANT = {"enterprise": "acme", "site": "wob", "area": "body", "line": "l3"}
TOPICS = ["acme/wob/body/l3/+/mvpose/#"]
# the results' outbox rows (a station without a PLC also queues its LINK_NO_PLC alarm's)
UNPUBLISHED = "SELECT count(*) FROM outbox WHERE topic LIKE '%/result' AND published_at IS NULL"
FIRST_RESULT = "SELECT payload FROM outbox WHERE topic LIKE '%/result' ORDER BY id LIMIT 1"


def _plant(port: int, poll_s: float = 0.05) -> Any:
    def edit(data: dict[str, Any]) -> None:
        data["plant"] = {**PLANT, "mqtt": {"host": "127.0.0.1", "port": port,
                                           "keepalive_s": 5, "poll_s": poll_s}}
    return edit


def _station(path: Path, data: Path, log: Path) -> subprocess.Popen[bytes]:
    env = dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=ENGINEER)
    with log.open("ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "server.cli", "station", "--station", str(path),
             "--data-dir", str(data), "--plc-port", "0", "--detect-processes", "0",
             "--log-level", "warning"], env=env, stdout=out, stderr=subprocess.STDOUT)


def _ready(client: StationClient, proc: subprocess.Popen[bytes], log: Path) -> bool:
    assert proc.poll() is None, f"the station process exited: {log.read_text()[-3000:]}"
    try:
        return bool(client.call("ping", timeout_s=1.0))
    except StationDownError:
        return False


def _rows(url: str, sql: str) -> list[Any]:
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            return list(conn.execute(text(sql)).all())
    finally:
        engine.dispose()


def test_every_record_once_through_outage_restart_and_will(tmp_path: Path) -> None:
    broker = Mosquitto(tmp_path)
    broker.start()
    sub = Subscriber(broker.port, TOPICS)
    path = station_file(tmp_path, "station1", relaxed_deadline, _plant(broker.port))
    data = tmp_path / "var"
    url = f"sqlite:///{data / 'mvpose.db'}"
    log = tmp_path / "station.log"
    client = StationClient(data / "station.sock")
    proc = _station(path, data, log)
    answers: list[TriggerAnswer] = []

    def trigger(n: int) -> None:
        for _ in range(n):
            k = len(answers) + 1
            got = client.trigger(part_id=f"P{k}", trigger_id=k)
            assert got.result_code == 0, got
            answers.append(got)

    try:
        wait_until("the station process answers", lambda: _ready(client, proc, log), START_S)
        online = wait_until("the retained online state",
                            lambda: [s for s in sub.on("/mvpose/state") if s["online"]])
        assert online[-1]["station"] == "station1"
        assert online[-1]["recipe"]["name"] and online[-1]["recipe"]["version"] >= 1

        trigger(5)
        wait_until("5 results at the subscriber", lambda: len(sub.results()) == 5)
        mqtt = client.status().part("mqtt")  # the station's status shows its publisher
        assert mqtt["connected"] and mqtt["broker"].endswith(f":{broker.port}")

        # the broker is killed mid-run (once its state holds what it acknowledged: a crash
        # before that loses it in the broker, docs/integration.md): triggers are answered as
        # before, the outbox keeps them
        wait_until("the 5 outbox rows marked published", lambda: _rows(
            url, UNPUBLISHED)[0][0] == 0)
        broker.stop(signal.SIGKILL)
        t = time.monotonic()
        trigger(5)
        assert time.monotonic() - t < 30
        wait_until("the 5 records in the outbox, unpublished", lambda: _rows(
            url, UNPUBLISHED)[0][0] == 5)
        assert len(sub.results()) == 5
        broker.start()
        wait_until("10 results after the broker's restart", lambda: len(sub.results()) == 10)

        # the station stops with unpublished rows (broker stopped): they go out after its restart
        broker.stop()
        trigger(3)
        wait_until("3 records in the outbox", lambda: _rows(
            url, UNPUBLISHED)[0][0] == 3)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, log.read_text()[-3000:]
        broker.start()
        proc = _station(path, data, log)
        wait_until("the restarted station process", lambda: _ready(client, proc, log), START_S)
        wait_until("13 results after the station's restart", lambda: len(sub.results()) == 13,
                   30)
        # each marked published once its PUBACK came (a SIGKILL before that: published again)
        wait_until("every outbox row marked published", lambda: _rows(
            url, UNPUBLISHED)[0][0] == 0)

        # SIGKILL: the broker publishes the last will, retained
        pid = client.status().pid
        os.kill(pid, signal.SIGKILL)
        proc.wait(timeout=10)
        will = wait_until("the last will", lambda: [
            s for s in sub.on("/mvpose/state") if not s["online"]], 30)
        assert will[-1]["reason"] == "connection lost" and will[-1]["station"] == "station1"
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
        sub.close()

    # a late consumer gets the retained state: offline (the will)
    late = Subscriber(broker.port, ["acme/wob/body/l3/station1/mvpose/state"], "late-consumer")
    try:
        retained = wait_until("the retained state", lambda: late.messages)
        assert retained[-1][2] and retained[-1][1]["online"] is False
    finally:
        late.close()
        broker.stop()

    # every record exactly once after deduplication, and as the database holds it
    got = sub.results()
    by_id = {p["id"] for p in got.values()}
    assert len(by_id) == len(got) == 13
    stored = {(r.station, r.seq): r for r in _rows(
        url, "SELECT id, station, seq, hash, trigger_id, part_id, result, reason_code "
             "FROM measurements")}
    assert set(got) == set(stored)
    for key, p in got.items():
        row = stored[key]
        assert (p["id"], p["hash"], p["trigger_id"], p["part_id"], p["result"],
                p["reason_code"], p["reason"]) == (
            row.id, row.hash, row.trigger_id, row.part_id, row.result, row.reason_code, "OK")
        assert p["offset"]["convention"] and len(p["offset"]["values"]) >= 6
        assert p["sigma_mm"] > 0 and p["recipe_version"] >= 1
        # every field of the result event, the fit's residual among them
        assert p["residual_rms_px"] > 0 and set(ResultEvent.__dataclass_fields__) <= set(p)
        assert p["convention"] == p["offset"]["convention"] and p["processing_ms"] > 0
    assert [a.result_id for a in answers] == sorted(p["result_id"] for p in got.values())
    assert _rows(url, UNPUBLISHED)[0][0] == 0
    body = json.loads(_rows(url, FIRST_RESULT)[0][0])
    assert body == got[("station1", 1)]


def test_a_record_is_published_once_committed_not_at_the_next_poll(tmp_path: Path) -> None:
    """The database thread wakes the publisher when a record's outbox row is committed: with
    the publisher's poll at 10 s, each result still reaches the subscriber within 2 s."""
    broker = Mosquitto(tmp_path)
    broker.start()
    sub = Subscriber(broker.port, TOPICS)
    path = station_file(tmp_path, "station1", relaxed_deadline, _plant(broker.port, poll_s=10))
    data = tmp_path / "var"
    log = tmp_path / "station.log"
    client = StationClient(data / "station.sock")
    proc = _station(path, data, log)
    try:
        wait_until("the station process answers", lambda: _ready(client, proc, log), START_S)
        wait_until("the retained online state",
                   lambda: [s for s in sub.on("/mvpose/state") if s["online"]], 30)
        for k in (1, 2, 3):
            got = client.trigger(part_id=f"P{k}", trigger_id=k)
            assert got.result_code == 0, got
            wait_until(f"result {k} at the subscriber", lambda k=k: len(sub.results()) == k, 2.0)
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        sub.close()
        broker.stop()


def test_plant_names_are_single_topic_levels(tmp_path: Path) -> None:
    from mvpose_core.station import StationFileError, load_station

    def wildcard(data: dict[str, Any]) -> None:
        data["plant"] = {**PLANT, "line": "l3/#", "mqtt": {"port": 1883}}

    path = station_file(tmp_path, "station1", wildcard)
    try:
        load_station(path)
    except StationFileError as err:
        assert "plant.line" in str(err) and "l3/#" in str(err), err
    else:
        raise AssertionError("a topic wildcard in plant.line was accepted")
    station = load_station(station_file(tmp_path, "station1", _plant(1883)))
    from server.station.mqtt import MqttPublisher

    pub = MqttPublisher.for_station(station)
    assert pub is not None and pub.result_topic == "acme/wob/body/l3/station1/mvpose/result"
    assert MqttPublisher.for_station(load_station(station_file(tmp_path, "station1"))) is None


def test_publisher_with_credentials_and_the_writer_outbox(tmp_path: Path,
                                                         monkeypatch: Any) -> None:
    """The durable writer's outbox (journal, database thread) and the publisher alone, against
    a broker that wants a password: a wrong one is refused and publishes nothing, the right one
    publishes every row; a clean stop leaves the retained state offline."""
    import numpy as np
    from records import make_record

    from mvpose_core.plantconfig import MqttConfig, PlantConfig
    from server.station.mqtt import MqttPublisher
    from server.store.outbox import Outbox, result_rows
    from server.store.writer import DurableWriter

    broker = Mosquitto(tmp_path, users={"st1": "s3cret", "mes": "r3ad"})
    broker.start()
    sub = Subscriber(broker.port, ["acme/#"], username="mes", password="r3ad")
    plant = PlantConfig(enterprise="acme", site="wob", area="body", line="l3")
    url = f"sqlite:///{tmp_path / 'store.db'}"
    writer = DurableWriter.open(url, "st1", tmp_path / "var",
                                outbox=result_rows("acme/wob/body/l3/st1/mvpose/result"))
    rng = np.random.default_rng(3)
    sealed = [writer.append(make_record(rng, "st1", trigger_id=k)) for k in range(1, 4)]
    assert writer.flush(10)
    outbox = Outbox(writer.engine, "st1")
    assert outbox.unpublished() == 3

    def publisher() -> MqttPublisher:
        pub = MqttPublisher("st1", plant, MqttConfig(port=broker.port, username="st1",
                                                     password_env="MQTT_PW", poll_s=0.05))
        pub.connect(writer.engine)
        return pub

    try:
        monkeypatch.setenv("MQTT_PW", "wrong")
        pub = publisher()
        wait_until("the broker refuses the wrong password",
                   lambda: pub.last_error and "refused" in pub.last_error)
        pub.stop()
        assert outbox.unpublished() == 3 and sub.on("/result") == []

        monkeypatch.setenv("MQTT_PW", "s3cret")
        pub = publisher()
        wait_until("3 results", lambda: len(sub.results()) == 3)
        wait_until("the rows marked published", lambda: outbox.unpublished() == 0)
        pub.stop()
        wait_until("the offline state", lambda: [
            s for s in sub.on("/st1/mvpose/state") if not s["online"]])
        assert sub.on("/st1/mvpose/state")[-1]["reason"] == "stopped"
    finally:
        sub.close()
        broker.stop()
        writer.close()
    got = sub.results()
    assert [(got[("st1", s.seq)]["id"], got[("st1", s.seq)]["hash"]) for s in sealed] == [
        (s.wait_id(1), s.hash) for s in sealed]
