"""The MQTT outbox's cost and the publisher's rate (docs/integration.md, "MQTT").

``python -m bench.mqtt_outbox [--postgres] [--n 1000]`` (--postgres: a throwaway PostgreSQL 15
cluster as the tests start it, fsync off; default: SQLite, synchronous FULL, in a temp dir)

1. The database thread's insert of one sealed link (its own transaction, as on a paced line),
   without and with its outbox row: what the outbox adds to the writer's commit (never to the
   trigger, which waits for the journal only).
2. The result message's size.
3. The publisher draining a backlog of ``n`` rows (a broker outage's worth) into Debian's
   Mosquitto on loopback (QoS 1, each row marked published after its PUBACK): messages/s.

Not part of ``make bench`` (it needs the mosquitto binary: apt-get install mosquitto).
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from bench.bench_store import station1_record
from mvpose_core.plantconfig import MqttConfig, PlantConfig
from server.station.mqtt import MqttPublisher
from server.store.chain import GENESIS
from server.store.db import create_store_engine, migrate
from server.store.measurements import Link, MeasurementRepository, normalized, seal_link
from server.store.outbox import Outbox, result_rows


def _links(station: str, n: int, rng: np.random.Generator) -> list[Link]:
    out, prev = [], GENESIS
    for seq in range(1, n + 1):
        rec = normalized(station1_record(rng, seq).model_copy(update={"station": station}))
        link = seal_link(station, seq, prev, datetime.now(UTC), rec)
        out.append(link)
        prev = link.hash
    return out


def _inserts(repo: MeasurementRepository, links: list[Link]) -> np.ndarray:
    ms = []
    for link in links:
        t = time.perf_counter()
        repo.insert_links([link])
        ms.append((time.perf_counter() - t) * 1e3)
    return np.array(ms[20:])


def _row(label: str, ms: np.ndarray) -> None:
    print(f"  {label:<34} median {np.median(ms):6.2f} ms   p99 {np.percentile(ms, 99):6.2f} ms")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--postgres", action="store_true", help="a throwaway PostgreSQL 15")
    ap.add_argument("--n", type=int, default=1000, help="records per measurement")
    args = ap.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="mvpose-outbox-"))
    url = f"sqlite:///{tmp / 'bench.db'}"
    cluster = None
    if args.postgres:
        sys.path.insert(0, str(Path(__file__).parents[1] / "tests" / "server"))
        from postgres import start_cluster, stop_cluster

        cluster = start_cluster()
        url = cluster[0].create_database()
    engine = create_store_engine(url)
    migrate(engine)
    rng = np.random.default_rng(0)
    suffix = datetime.now(UTC).strftime("%H%M%S")
    plain, boxed = f"plain-{suffix}", f"boxed-{suffix}"
    topic = f"acme/plant1/body-shop/line3/{boxed}/mvpose/result"
    print(f"database: {engine.url.get_backend_name()}, {args.n} links each")
    _row("insert one link", _inserts(MeasurementRepository(engine, plain), _links(plain, args.n,
                                                                                 rng)))
    _row("insert one link + its outbox row", _inserts(
        MeasurementRepository(engine, boxed, result_rows(topic)), _links(boxed, args.n, rng)))
    outbox = Outbox(engine, boxed)
    sizes = [len(p.payload) for p in outbox.pending(limit=args.n)]
    print(f"  result message: {int(np.median(sizes))} bytes (median)")

    exe = shutil.which("mosquitto") or shutil.which("mosquitto", path="/usr/sbin")
    if exe is None:
        print("  mosquitto not installed: the publisher's rate is not measured")
        return 1
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    conf = tmp / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\nuser root\n")
    broker = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    try:
        plant = PlantConfig(enterprise="acme", site="plant1", area="body-shop", line="line3")
        pub = MqttPublisher(boxed, plant, MqttConfig(port=port, poll_s=0.05))
        t = time.perf_counter()
        pub.connect(engine)
        while outbox.unpublished():
            time.sleep(0.05)
            assert time.perf_counter() - t < 120, "the backlog was not published in 120 s"
        dt = time.perf_counter() - t
        pub.stop()
        print(f"  backlog of {args.n} published and marked: {dt:.2f} s, "
              f"{args.n / dt:.0f} messages/s (QoS 1, loopback)")
    finally:
        broker.terminate()
        broker.wait(timeout=10)
        engine.dispose()
        if cluster is not None:
            stop_cluster(*cluster)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
