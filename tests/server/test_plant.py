"""Plant in a box: the three station files of deploy/compose.plant.yaml as three station
processes, one PostgreSQL 15 server, one Mosquitto, three PLC twins over Modbus/TCP.

Each station's twin triggers it while the others run. Midway the broker is killed (SIGKILL)
while the stations go on triggering, and one station is killed (SIGKILL) with records its outbox
has not published; the other two keep triggering; then both come back and every station
triggers again. At the end a subscriber has every record of every station exactly once
after deduplication by id, and the database holds exactly those records.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import yaml
from mqtt_broker import Mosquitto, Subscriber, wait_until
from postgres import PostgresCluster
from sqlalchemy import create_engine, text
from stations import ENGINEER, ROOT

from server.loopback import attach_twin, detach_twin
from server.station.client import StationClient, StationDownError

START_S = 150.0  # three station processes starting together on a loaded 2-core machine
NAMES = ("line3-s1", "line3-s2", "line3-s3")


class Proc:
    """One station process (``python -m server.cli station``) on a plant station file."""

    def __init__(self, tmp: Path, name: str, broker_port: int, url: str) -> None:
        data = yaml.safe_load((ROOT / "deploy" / "plant" / f"{name}.yaml").read_text())
        data["deadline_ms"] = 1000.0  # a shared, loaded machine (tests/server/stations.py)
        data["plant"]["mqtt"] = dict(data["plant"]["mqtt"], port=broker_port, poll_s=0.05)
        self.name = name
        self.file = tmp / f"{name}.yaml"
        self.file.write_text(yaml.safe_dump(data, sort_keys=False))
        self.data = tmp / name
        self.log = tmp / f"{name}.log"
        self.url = url
        self.client = StationClient(self.data / "station.sock")
        self.proc: subprocess.Popen[bytes] | None = None
        self.answers: list[tuple[int, int, int]] = []  # trigger id, code, result id

    def start(self) -> None:
        env = dict(os.environ, MVPOSE_BOOTSTRAP_TOKEN=ENGINEER, MVPOSE_DATABASE_URL=self.url)
        with self.log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "server.cli", "station", "--station", str(self.file),
                 "--data-dir", str(self.data), "--plc-port", "0", "--detect-processes", "0",
                 "--log-level", "warning"], env=env, stdout=out, stderr=subprocess.STDOUT)

    def ready(self) -> bool:
        assert self.proc is not None
        assert self.proc.poll() is None, f"{self.name} exited: {self.log.read_text()[-3000:]}"
        try:
            return bool(self.client.call("ping", timeout_s=1.0))
        except StationDownError:
            return False

    def modbus_port(self) -> int:
        return int(self.client.status().links["modbus"]["port"])

    async def run(self, n: int) -> None:
        twin, beat = await attach_twin(await asyncio.to_thread(self.modbus_port), poll_s=0.005)
        try:
            for _ in range(n):
                k = len(self.answers) + 1
                status = await twin.cycle(k, part_id=f"{self.name}-{k}", timeout=20.0)
                self.answers.append((k, status.result_code, status.result_id))
        finally:
            await detach_twin(twin, beat)

    def stop(self, sig: int = signal.SIGTERM) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)
            self.proc.wait(timeout=30)


def _wait_ready(procs: list[Proc]) -> None:
    wait_until("the station processes answer", lambda: all(p.ready() for p in procs), START_S)


async def test_plant_in_a_box_every_record_once(tmp_path: Path,
                                                postgres_cluster: PostgresCluster) -> None:
    url = postgres_cluster.create_database()
    broker = Mosquitto(tmp_path)
    broker.start()
    sub = Subscriber(broker.port, ["acme/plant1/body-shop/line3/+/mvpose/result"])
    procs = [Proc(tmp_path, name, broker.port, url) for name in NAMES]
    try:
        for p in procs:
            p.start()
        await asyncio.to_thread(_wait_ready, procs)
        await asyncio.gather(*(p.run(4) for p in procs))
        await asyncio.to_thread(wait_until, "the first 12 records at the subscriber",
                                lambda: len(sub.results()) == 12, 30)

        # midway: the broker is killed, the stations go on (their outboxes fill), station 2 is
        # killed with unpublished rows, stations 1 and 3 go on
        await asyncio.to_thread(broker.stop, signal.SIGKILL)
        await asyncio.gather(*(p.run(3) for p in procs))
        down = procs[1]
        down.stop(signal.SIGKILL)
        await asyncio.gather(procs[0].run(3), procs[2].run(3))
        assert len(sub.results()) == 12
        await asyncio.to_thread(broker.start)
        down.start()
        await asyncio.to_thread(_wait_ready, [down])
        await asyncio.gather(*(p.run(2) for p in procs))

        expected = sum(len(p.answers) for p in procs)
        assert expected == 4 * 3 + 3 * 3 + 3 * 2 + 2 * 3
        await asyncio.to_thread(wait_until, "every record at the subscriber",
                                lambda: len(sub.results()) == expected, 60)
    finally:
        for p in procs:
            p.stop()
        sub.close()
        broker.stop()

    for p in procs:
        assert [code for _, code, _ in p.answers] == [0] * len(p.answers), (p.name, p.answers)
        ids = [rid for _, _, rid in p.answers]
        assert ids == list(range(1, len(ids) + 1)), (p.name, ids)
    got = sub.results()
    engine = create_engine(url)
    try:
        with engine.connect() as conn:
            stored = {(r.station, r.seq): r for r in conn.execute(text(
                "SELECT id, station, seq, hash, trigger_id FROM measurements")).all()}
    finally:
        engine.dispose()
    assert set(got) == set(stored) == {(p.name, rid) for p in procs for _, _, rid in p.answers}
    assert len({m["id"] for m in got.values()}) == len(got)  # dedup by id: the same keys
    for key, m in got.items():
        row: Any = stored[key]
        assert (m["id"], m["hash"], m["trigger_id"]) == (row.id, row.hash, row.trigger_id)
    dupes = len(sub.on("/mvpose/result")) - len(got)
    print(f"plant: {len(got)} records, {dupes} duplicates delivered (deduplicated by id)")
