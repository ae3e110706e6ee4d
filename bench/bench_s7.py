"""S7 link benchmark: trigger → answer p99 through S7 (poll 5 ms) against Modbus/TCP, measured in
the same run, twice: through station 1 (simulated cameras, the real pipeline and store: the
issue's target) and with an instant pipeline (the links' own cost, for the record).

The PLC runs in a process of its own (a PLC is another device; bench.twin_process does the same
for Modbus): over Modbus the twin is the client of the station's Modbus/TCP server; over S7 the
child hosts the CPU (python-snap7's server) and runs the twin's program on its DBs, which the
station's S7 link polls every 5 ms and writes. Each trigger comes a random 0..5 ms after READY,
as a part's arrival is not timed to the poll. As in production, both sides run under the
real-time FIFO policy when they may: this process at the station's trigger priority (10), the
PLC's at ``MVPOSE_BENCH_TWIN_PRIORITY`` (default 20). The target (issue 24): through the
station, S7's p99 within the poll period plus 1.1 × Modbus's p99; that line says OK or MISSED.
With an instant pipeline that margin is a few hundredths of a millisecond, less than python-
snap7's own request cost; that line is printed for the record only.
"""

from __future__ import annotations

import asyncio
import gc
import multiprocessing as mp
import os
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager
from functools import partial
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from bench.bench_plc import InstantPipeline
from bench.timing import Timing
from drivers.links.layout import Control, Status
from drivers.links.modbus import ModbusLink, ModbusLinkConfig
from drivers.links.modbus.twin import ModbusPort
from drivers.links.s7 import S7Link, S7LinkConfig
from drivers.links.s7.twin import S7Cpu, S7Port
from drivers.links.twin import PlcPort, PlcStatus, PlcTwin

POLL_S = 0.005
N_INSTANT = 400
N_STATION = 150
WARMUP = 20
ROOT = Path(__file__).resolve().parents[1]


class Handler(InstantPipeline):
    """The instant pipeline with recipe 1 selected (what the links ask at start)."""

    def selected_recipe(self) -> int:
        return 1


def _realtime(priority: int, who: str) -> None:
    """This thread (and the threads it starts) under SCHED_FIFO at ``priority`` (0: not)."""
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (OSError, AttributeError) as err:
            print(f"{who}: normal scheduler ({err})", file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- the PLC (child)
def _toggled(before: bool, status: PlcStatus) -> bool:
    return status.has(Status.DONE_TOGGLE) != before


async def _cycles(twin: PlcTwin, n: int, rng: np.random.Generator) -> np.ndarray:
    """Trigger written → answer read, as the PLC sees it, for ``n`` handshakes."""
    await twin.connect()
    await twin.enable()
    status = await twin.wait_for(lambda s: s.has(Status.READY | Status.ERROR), 60.0, "READY")
    if status.has(Status.ERROR):
        await twin.reset_error(10.0)
    samples = np.empty(n)
    for i in range(WARMUP + n):
        before = await twin.wait_for(lambda s: s.has(Status.READY), 30.0, "READY")
        toggle = before.has(Status.DONE_TOGGLE)
        await asyncio.sleep(rng.uniform(0.0, POLL_S))
        t0 = time.perf_counter()
        await twin.write_trigger(i + 1)
        answer = await twin.wait_for(partial(_toggled, toggle), 30.0, "the answer")
        took = time.perf_counter() - t0
        if answer.trigger_id != i + 1:
            raise RuntimeError(f"trigger {i + 1}: the answer echoes {answer.trigger_id}")
        await twin.set_control(Control.TRIGGER_ENABLE | Control.RESULT_ACK)
        await twin.wait_for(lambda s: not s.has(Status.RESULT_VALID), 30.0, "the ack")
        if i >= WARMUP:
            samples[i - WARMUP] = took * 1e3
    twin.close()
    return samples


def _plc(pipe: Connection) -> None:
    """The child: runs PLC programs on request. ("s7",) starts a CPU and sends its link block;
    ("modbus", port) connects to the station's port; then ("go", n) runs n cycles and sends
    the samples. ("stop",) ends it. A CPU stops at the next request, after the station's link
    (not before: the link would log a lost PLC)."""
    _realtime(int(os.environ.get("MVPOSE_BENCH_TWIN_PRIORITY", "20")), "PLC")
    cpu: S7Cpu | None = None
    port: Callable[[], PlcPort] | None = None  # made in the loop that uses it (pymodbus)
    while True:
        msg = pipe.recv()
        if msg[0] != "go" and cpu is not None:  # the station's link has stopped by now
            cpu.stop()
            cpu = None
        if msg[0] == "s7":
            cpu = S7Cpu().start()
            port = partial(S7Port, cpu)
            pipe.send(cpu.settings)
        elif msg[0] == "modbus":
            port = partial(ModbusPort, "127.0.0.1", msg[1])
            pipe.send(None)
        elif msg[0] == "go":
            assert port is not None
            poll = 0.0002 if cpu is not None else 0.0  # a PLC scans its own DBs

            async def run(make: Callable[[], PlcPort], n: int, poll_s: float) -> np.ndarray:
                return await _cycles(PlcTwin(make(), poll_s=poll_s), n,
                                     np.random.default_rng(1))

            try:
                pipe.send(asyncio.run(run(port, msg[1], poll)))
            except Exception as err:  # noqa: BLE001 - the parent reports it
                pipe.send(err)
            port = None
        else:
            return


async def _answer(pipe: Connection, timeout: float = 300.0) -> Any:
    """The child's next message (its exception re-raised), waiting on the loop."""
    deadline = time.monotonic() + timeout
    while not pipe.poll():
        if time.monotonic() > deadline:
            raise TimeoutError(f"the PLC process did not answer within {timeout:g} s")
        await asyncio.sleep(0.01)
    got = pipe.recv()
    if isinstance(got, Exception):
        raise got
    return got


async def _run_plc(pipe: Connection, n: int) -> np.ndarray:
    pipe.send(("go", n))
    samples: np.ndarray = await _answer(pipe)
    return samples


# --------------------------------------------------------------------------- the station side
async def _connected(link: Any) -> None:
    deadline = time.monotonic() + 60
    while not link.status().get("connected", True):
        if time.monotonic() > deadline:
            raise RuntimeError(f"the {link.name} link did not connect: {link.status()}")
        await asyncio.sleep(0.01)


async def _instant(bus: str, pipe: Connection) -> np.ndarray:
    if bus == "modbus":
        link: Any = ModbusLink(ModbusLinkConfig(port=0, watchdog_s=0),
                               Handler())  # type: ignore[arg-type]
        await link.start()
        pipe.send(("modbus", link.port))
    else:
        pipe.send(("s7",))
        block = {**await _answer(pipe), "poll_s": POLL_S, "watchdog_s": 0}
        link = S7Link(S7LinkConfig.model_validate(block), Handler())  # type: ignore[arg-type]
        await link.start()
    try:
        if bus == "modbus":
            await _answer(pipe)
        await _connected(link)
        return await _run_plc(pipe, N_INSTANT)
    finally:
        await link.stop()


def _station(bus: str, pipe: Connection,
             data: Path) -> Callable[[], AbstractAsyncContextManager[Any]]:
    from server.loopback import running_server
    from server.settings import Settings
    from server.station.core import StationOptions

    settings = Settings(station=ROOT / "deploy" / "stations" / "station1.yaml",
                        data_dir=data / bus, bootstrap_token="mvp_bench-" + "x" * 24)

    @asynccontextmanager
    async def run() -> AsyncIterator[Any]:
        links: dict[str, dict[str, Any]] = {"modbus": {"watchdog_s": 0}}
        if bus == "s7":
            pipe.send(("s7",))
            links = {"s7": {**await _answer(pipe), "poll_s": POLL_S, "watchdog_s": 0},
                     "modbus": {"enabled": False}}
        async with running_server(settings, StationOptions(sim_seed=1), http_port=None,
                                  links=links) as rs:
            if bus == "modbus":
                pipe.send(("modbus", rs.runtime.link_port("modbus")))
                await _answer(pipe)
            link = rs.runtime.link(bus)
            await _connected(link)
            yield rs
    return run


async def _through_station(bus: str, pipe: Connection, data: Path) -> np.ndarray:
    async with _station(bus, pipe, data)():
        return await _run_plc(pipe, N_STATION)


def main() -> int:
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    plc = ctx.Process(target=_plc, args=(child,), name="plc")
    plc.start()
    _realtime(10, "links")
    try:
        with tempfile.TemporaryDirectory(prefix="bench-s7-") as tmp:
            station = {bus: asyncio.run(_through_station(bus, parent, Path(tmp)))
                       for bus in ("modbus", "s7")}
        gc_was = gc.isenabled()
        gc.disable()
        try:
            instant = {bus: asyncio.run(_instant(bus, parent)) for bus in ("modbus", "s7")}
        finally:
            if gc_was:
                gc.enable()
    finally:
        parent.send(("stop",))
        plc.join(10)
        if plc.is_alive():
            plc.kill()
    ok = True
    for what, runs in (("station 1", station), ("instant pipeline", instant)):
        modbus = Timing(f"{what}, Modbus/TCP: trigger -> answer", runs["modbus"])
        s7 = Timing(f"{what}, S7 poll {POLL_S * 1e3:g} ms: trigger -> answer", runs["s7"])
        print(modbus.line())
        print(s7.line(modbus))
        limit = POLL_S * 1e3 + 1.1 * modbus.p99
        verdict = "OK" if s7.p99 <= limit else "MISSED"
        if what == "station 1":
            ok = verdict == "OK"
        else:
            verdict += " (for the record; not a target)"
        print(f"{what}: S7 p99 {s7.p99:.3f} ms vs poll + 1.1 x Modbus p99 = {limit:.3f} ms: "
              f"{verdict}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
