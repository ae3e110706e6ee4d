"""PROFINET link benchmark: trigger → result through RT_CLASS_1 cyclic data at a 4 ms cycle,
against the Modbus/TCP figure measured in the same run (the same PLC twin program, the same
instant pipeline). Target: p99 ≤ cycle + 1.1 × the Modbus p99 (issue 25). The cycle's jitter
(p99 − p50 of the frame intervals) is reported for both ends.

The IO-controller is our own twin (drivers/links/profinet/twin.py: a process of its own, frames
both ways every cycle, no round trip to the twin) on a veth pair whose controller end is in a
network namespace (root needed; the benchmark says so and skips otherwise). RT_CLASS_1 frames
are cyclic in both directions, so a trigger waits up to one cycle for the controller's next
output frame and the answer up to one for the device's next input frame. profinet-py (the
tests' independent controller, driven over a pipe) is a second line, reported only, when the
test extras are installed.
"""

from __future__ import annotations

import asyncio
import gc
import os
import time

import numpy as np

from bench.bench_enip import Pipeline, _handshakes
from bench.bench_plc import _toggled
from bench.timing import Timing, check
from drivers.links.layout import Control, Status
from drivers.links.modbus import ModbusLink
from drivers.links.modbus.settings import ModbusLinkConfig
from drivers.links.modbus.twin import modbus_twin
from drivers.links.profinet import ProfinetLink
from drivers.links.profinet.netns import VethLine, why_not
from drivers.links.profinet.settings import ProfinetLinkConfig
from drivers.links.profinet.twin import ProfinetPort
from drivers.links.twin import PlcPort, PlcTwin

CYCLE_MS = 4.0
N = 300
NAME = "mvpose-bench"


async def _triggers(twin: PlcTwin, n: int) -> np.ndarray:
    await twin.enable()
    out = np.empty(n)
    for i in range(n):
        ready = await twin.wait_for(lambda s: s.has(Status.READY), 5.0, "READY")
        toggle = ready.has(Status.DONE_TOGGLE)
        t0 = time.perf_counter()
        await twin.write_trigger(i + 1)
        answer = await twin.wait_for(_toggled(toggle), 5.0, "result")
        out[i] = (time.perf_counter() - t0) * 1e3
        if answer.trigger_id != i + 1:
            raise RuntimeError(f"trigger {i + 1}: got {answer.trigger_id}")
        await twin.set_control(Control.TRIGGER_ENABLE | Control.RESULT_ACK)
        await twin.wait_for(lambda s: not s.has(Status.RESULT_VALID), 5.0, "ack")
    return out


async def _stats_after(link: ProfinetLink, since: float) -> dict[str, object]:
    """The device's status once a stats message newer than ``since`` arrived (every 1 s)."""
    while link.stats_at <= since:
        await asyncio.sleep(0.1)
    return link.status()


async def _profinet(n: int, ours: bool) -> tuple[np.ndarray, dict[str, object],
                                                  dict[str, object]]:
    """``n`` trigger → result times through the device, and the device's and the controller's
    status (cycle p50 and jitter); the controller is ours, or profinet-py."""
    line = VethLine.create()
    try:
        link = ProfinetLink(ProfinetLinkConfig(interface=line.device_if, station_name=NAME,
                                               rpc_host=line.device_ip, watchdog_s=0),
                            Pipeline())  # type: ignore[arg-type]
        await link.start()
        try:
            if ours:
                port = ProfinetPort(line.controller_if, NAME, netns=line.ns,
                                    cycle_ms=CYCLE_MS)
                twin = PlcTwin(port)
                await twin.connect()
                try:
                    out = await _triggers(twin, n)
                    t = time.monotonic()
                    status = await _stats_after(link, t)
                    while port.stats_at <= t:
                        await asyncio.sleep(0.1)
                    return out, status, port.stats
                finally:
                    twin.close()
            from tests.drivers import profinet_peer as peer

            net = peer.Net(line.ns, line.device_if, line.controller_if, line.device_ip,
                           line.controller_ip)
            async with peer.controller(net) as ctl:
                await ctl.run_ar(NAME, reduction_ratio=round(CYCLE_MS))
                py_port: PlcPort = peer.ControllerPort(ctl)
                twin = PlcTwin(py_port)
                await twin.connect()
                out = await _triggers(twin, n)
                return out, await _stats_after(link, time.monotonic()), {}
        finally:
            await link.stop()
    finally:
        line.remove()


async def _run(with_py: bool) -> tuple[Timing, Timing, dict[str, object], dict[str, object],
                                       Timing | None]:
    def modbus() -> ModbusLink:
        return ModbusLink(ModbusLinkConfig(port=0, watchdog_s=0), Pipeline())  # type: ignore[arg-type]

    def mtwin(port: int) -> PlcTwin:
        return modbus_twin("127.0.0.1", port)

    await _handshakes(modbus(), mtwin, 20)
    mb = await _handshakes(modbus(), mtwin, N)
    await _profinet(20, True)  # warm the path
    pn, device, controller = await _profinet(N, True)
    py = None
    if with_py:
        py_ms, _, _ = await _profinet(N, False)
        py = Timing("  profinet-py as the controller (reported only)", py_ms)
    return (Timing("Modbus/TCP: trigger written -> result seen", mb),
            Timing(f"PROFINET (cycle {CYCLE_MS:g} ms): trigger -> result", pn), device,
            controller, py)


def main() -> int:
    why = why_not()
    if why is not None:
        print(f"PROFINET benchmark skipped: {why}")
        return 0
    try:
        import profinet  # noqa: F401 - the tests' independent controller, reported only
        with_py = True
    except ImportError:
        with_py = False
    gc_was = gc.isenabled()
    gc.disable()
    try:
        modbus, pn, device, controller, py = asyncio.run(_run(with_py))
    finally:
        if gc_was:
            gc.enable()
    print(f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(modbus.line())
    print(pn.line(modbus))
    print(f"cycle: the device's input frames every {device.get('cycle_p50_ms')} ms (p50), "
          f"jitter (p99 - p50) {device.get('cycle_jitter_ms')} ms; the controller's output "
          f"frames every {controller.get('cycle_p50_ms')} ms, jitter "
          f"{controller.get('cycle_jitter_ms')} ms")
    if py is not None:
        print(py.line(modbus))
    ok = check(f"PROFINET p99 (cycle + 1.1 x Modbus p99 = {CYCLE_MS:g} + 1.1 x "
               f"{modbus.p99:.3f})", pn.p99, CYCLE_MS + 1.1 * modbus.p99)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
