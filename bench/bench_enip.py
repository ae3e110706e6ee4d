"""EtherNet/IP link benchmark: trigger → result through class 1 I/O at RPI 4 ms, against the
Modbus/TCP figure measured in the same run (the same PLC twin program, the same instant
pipeline, each through its link). Target: p99 ≤ RPI + 1.1 × the Modbus p99 (issue 24).

The twin opens its connection with the change-of-state trigger (the answer leaves as soon as
it is in the input image; RPI is the background rate) and sends its outputs every RPI, as a
scanner does: the trigger waits for the next O→T datagram, up to one RPI.
"""

from __future__ import annotations

import asyncio
import gc
import time
from collections.abc import Callable

import numpy as np

from bench.bench_plc import InstantPipeline, _toggled
from bench.timing import Timing, check
from drivers.links.enip import EnipLink
from drivers.links.enip.settings import EnipLinkConfig
from drivers.links.enip.twin import enip_twin
from drivers.links.layout import Control, Status
from drivers.links.modbus import ModbusLink
from drivers.links.modbus.settings import ModbusLinkConfig
from drivers.links.modbus.twin import modbus_twin
from drivers.links.twin import PlcTwin

RPI_MS = 4.0
N = 500


class Pipeline(InstantPipeline):
    def selected_recipe(self) -> int:
        return 1


async def _handshakes(link: ModbusLink | EnipLink, twin_for: Callable[[int], PlcTwin],
                      n: int) -> np.ndarray:
    """``n`` trigger → result times (ms) through ``link``, by the twin ``twin_for(port)``."""
    await link.start()
    try:
        twin = twin_for(link.port)
        await twin.connect()
        try:
            await twin.enable()
            out = np.empty(n)
            for i in range(n):
                ready = await twin.wait_for(lambda s: s.has(Status.READY), what="READY")
                toggle = ready.has(Status.DONE_TOGGLE)
                t0 = time.perf_counter()
                await twin.write_trigger(i + 1)
                answer = await twin.wait_for(_toggled(toggle), what="result")
                out[i] = (time.perf_counter() - t0) * 1e3
                if answer.trigger_id != i + 1:
                    raise RuntimeError(f"{link.name} trigger {i + 1}: got {answer.trigger_id}")
                await twin.set_control(Control.TRIGGER_ENABLE | Control.RESULT_ACK)
                await twin.wait_for(lambda s: not s.has(Status.RESULT_VALID), what="ack")
            return out
        finally:
            twin.close()
    finally:
        await link.stop()


async def _run() -> tuple[Timing, Timing]:
    def modbus() -> ModbusLink:
        return ModbusLink(ModbusLinkConfig(port=0, watchdog_s=0), Pipeline())  # type: ignore[arg-type]

    def enip() -> EnipLink:
        return EnipLink(EnipLinkConfig(port=0, io_port=0, watchdog_s=0),
                        Pipeline())  # type: ignore[arg-type]

    def mtwin(port: int) -> PlcTwin:
        return modbus_twin("127.0.0.1", port)

    def etwin(port: int) -> PlcTwin:
        return enip_twin("127.0.0.1", port, rpi_ms=RPI_MS)

    await _handshakes(modbus(), mtwin, 20)  # warm both paths
    await _handshakes(enip(), etwin, 20)
    mb = await _handshakes(modbus(), mtwin, N)
    en = await _handshakes(enip(), etwin, N)
    return (Timing("Modbus/TCP: trigger written -> result seen", mb),
            Timing(f"EtherNet/IP (RPI {RPI_MS:g} ms): trigger -> result", en))


def main() -> int:
    gc_was = gc.isenabled()
    gc.disable()
    try:
        modbus, enip = asyncio.run(_run())
    finally:
        if gc_was:
            gc.enable()
    print(modbus.line())
    print(enip.line(modbus))
    ok = check(f"EtherNet/IP p99 (RPI + 1.1 x Modbus p99 = {RPI_MS:g} + 1.1 x "
               f"{modbus.p99:.3f})", enip.p99, RPI_MS + 1.1 * modbus.p99)
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
