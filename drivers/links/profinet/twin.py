"""The PLC twin's PROFINET side: our IO-controller (:mod:`.controller`) in a process of its
own (``python -m drivers.links.profinet.twin``, optionally inside a network namespace), and
:class:`ProfinetPort`, the twin's :class:`~drivers.links.twin.PlcPort` over it.

The process holds a raw socket on the controller's interface and the RPC socket (UDP 34964,
where the device sends ApplicationReady); its cycle never waits for the twin's GIL. It talks to
the port over a SEQPACKET socketpair (the descriptor is the second argument), one message a
packet and never a round trip: to the child ``O`` + the OUTPUT block (big-endian) and ``Q``
(release and stop); to the port ``I`` + the INPUT block whenever the device's input data
changed, ``E`` + a JSON event (``{"kind", "text"}``: started, error, the controller's events)
and ``S`` + JSON stats every second. A lost or refused AR is started again after a second, as
a PLC does.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import select
import socket
import subprocess
import time
from collections import deque
from typing import Any

from ...errors import DriverInitError
from .. import layout
from ..layout import ByteOrder
from . import child, rpc
from . import frames as fr
from .controller import Controller
from .device import Out
from .transport import _jitter, open_sockets, realtime

START_S = 30.0
RESTART_S = 1.0
STATS_EVERY_S = 1.0


def serve(cfg: dict[str, Any], pair: socket.socket) -> None:
    """The controller's loop: sockets, the cycle, the port's messages."""

    def event(kind: str, text: str) -> None:
        pair.send(b"E" + json.dumps({"kind": kind, "text": text}).encode())

    try:
        raw, udp, mac, _ip = open_sockets(cfg["interface"], "0.0.0.0", rpc.RPC_PORT,
                                          "the PROFINET PLC twin")
    except OSError as err:
        event("error", str(err))
        return

    def new() -> Controller:
        return Controller(mac, cfg["station_name"], cycle_ms=cfg["cycle_ms"],
                          data_hold_factor=cfg["data_hold_factor"])

    ctl = new()
    outputs = ctl.output_image
    # a hardware PLC's cycle does not wait for the host's other work; this one's neither
    scheduling = realtime(cfg["realtime_priority"])
    event("started", f"PROFINET PLC twin on {cfg['interface']} ({fr.mac_text(mac)}), "
          f"{scheduling}, looking for {cfg['station_name']!r}")
    intervals: deque[float] = deque(maxlen=2000)  # between output frames sent, for the jitter
    last_cyclic = 0.0
    restart_at: float | None = None
    next_stats = time.monotonic()

    def emit(out: Out) -> None:
        nonlocal last_cyclic, restart_at
        for frame in out.frames:
            with contextlib.suppress(OSError):  # the link down: the data hold time tells
                raw.send(frame)
        if out.cyclic:
            t = time.monotonic()
            if last_cyclic:
                intervals.append(t - last_cyclic)
            last_cyclic = t
        for data, addr in out.datagrams:
            with contextlib.suppress(OSError):
                udp.sendto(data, addr)
        for ev in out.events:
            event(ev.kind, ev.text)
            if ev.kind in ("failed", "lost"):
                restart_at = time.monotonic() + RESTART_S
        if out.output is not None:
            pair.send(b"I" + out.output)

    emit(ctl.start(time.monotonic()))
    while True:
        now = time.monotonic()
        deadline = ctl.next_deadline(now) if restart_at is None else restart_at
        ready, _, _ = select.select([raw, udp, pair], [], [], max(0.0, deadline - now))
        now = time.monotonic()
        if pair in ready:
            msg = pair.recv(4096)
            if not msg or msg[:1] == b"Q":
                emit(ctl.release(now))
                return
            if msg[:1] == b"O" and len(msg) - 1 == layout.OUTPUT_SIZE:
                outputs = ctl.output_image = msg[1:]
        if raw in ready:
            for _ in range(64):
                try:
                    frame = raw.recv(2048, socket.MSG_DONTWAIT)
                except OSError:
                    break
                emit(ctl.on_frame(frame, now))
        if udp in ready:
            with contextlib.suppress(OSError):
                data, addr = udp.recvfrom(8192)
                emit(ctl.on_datagram(data, addr, now))
        if restart_at is not None and now >= restart_at:
            restart_at = None
            ctl = new()
            ctl.output_image = outputs
            emit(ctl.start(now))
        emit(ctl.tick(time.monotonic()))
        if now >= next_stats:
            st = ctl.stats
            pair.send(b"S" + json.dumps({
                **{k: v for k, v in vars(st).items() if k != "last_errors"},
                "last_errors": st.last_errors[-5:], "phase": ctl.phase,
                "scheduling": scheduling,
                **_jitter(intervals)}).encode())
            next_stats = now + STATS_EVERY_S


class ProfinetPort:
    """The twin's port: the controller process on ``interface`` (inside network namespace
    ``netns`` if given), connected to the device named ``station_name``. :meth:`connect`
    returns once the AR exchanges data; :meth:`read_inputs` gives the device's latest input
    data, waiting up to one cycle for a new one (a PLC program reads its inputs once a bus
    cycle), and :meth:`write_outputs` goes out with the next cycle's frame."""

    byte_order = ByteOrder.BIG
    word_order = ByteOrder.BIG.word_order

    def __init__(self, interface: str, station_name: str, *, netns: str | None = None,
                 cycle_ms: float = 4.0, data_hold_factor: int = 100,
                 realtime_priority: int = 10) -> None:
        # the data hold time is 100 cycles by default: a Python controller on a shared host
        # can miss cycles that a hardware PLC does not (the device's own is the controller's)
        Controller(bytes(6), station_name, cycle_ms=cycle_ms,
                   data_hold_factor=data_hold_factor)  # the settings' errors, here
        self.cfg = {"interface": interface, "station_name": station_name,
                    "cycle_ms": cycle_ms, "data_hold_factor": data_hold_factor,
                    "realtime_priority": realtime_priority}
        self.netns = netns
        self.cycle_s = cycle_ms / 1000
        self.inputs = bytes(layout.INPUT_SIZE)
        self.outputs = bytearray(layout.OUTPUT_SIZE)
        self.events: list[dict[str, Any]] = []  # the controller's last 20
        self.stats: dict[str, Any] = {}  # the controller's, every second
        self.stats_at = 0.0  # when they came (monotonic)
        self._proc: subprocess.Popen[bytes] | None = None
        self._pair: socket.socket | None = None
        self._fresh = asyncio.Event()
        self._running: asyncio.Future[None] | None = None

    async def connect(self) -> None:
        prefix = ["ip", "netns", "exec", self.netns] if self.netns else []
        self._proc, self._pair = child.spawn("drivers.links.profinet.twin", self.cfg, prefix)
        loop = asyncio.get_running_loop()
        self._running = loop.create_future()
        loop.add_reader(self._pair.fileno(), self._read)
        try:
            await asyncio.wait_for(asyncio.shield(self._running), START_S)
        except TimeoutError:
            why = next((e["text"] for e in reversed(self.events)
                        if e["kind"] in ("failed", "lost")), "no answer")
            self.abort()
            raise DriverInitError(f"PROFINET PLC twin: no AR with {self.cfg['station_name']!r}"
                                  f" within {START_S:g} s ({why})") from None
        except BaseException:
            self.abort()
            raise

    def _read(self) -> None:
        assert self._pair is not None
        messages, ended = child.received(self._pair)
        for kind, body in messages:
            if kind == b"I":
                self.inputs = body
                self._fresh.set()
            elif kind == b"E":
                ev = json.loads(body)
                self.events = [*self.events[-19:], ev]
                done = self._running is None or self._running.done()
                if ev["kind"] == "error" and not done:
                    assert self._running is not None
                    self._running.set_exception(DriverInitError(ev["text"]))
                elif ev["kind"] == "running" and not done:
                    assert self._running is not None
                    self._running.set_result(None)
            elif kind == b"S":
                self.stats = json.loads(body)
                self.stats_at = time.monotonic()
        if ended:
            self._drop_reader()
            if self._running is not None and not self._running.done():
                self._running.set_exception(DriverInitError(
                    "the PROFINET PLC twin's process ended"))

    async def read_inputs(self) -> bytes:
        if not self._fresh.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._fresh.wait(), self.cycle_s)
        self._fresh.clear()
        return self.inputs

    async def write_outputs(self, offset: int, data: bytes) -> None:
        self.outputs[offset:offset + len(data)] = data
        if self._pair is None:
            raise DriverInitError("the PROFINET PLC twin is not connected")
        self._pair.send(b"O" + bytes(self.outputs))

    def _drop_reader(self) -> None:
        if self._pair is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(self._pair.fileno())

    def close(self) -> None:
        """Release the AR and stop the process."""
        self._stop(release=True)

    def abort(self) -> None:
        """Stop without a Release, like a PLC switched off: the device's data hold time
        ends the AR."""
        self._stop(release=False)

    def _stop(self, release: bool) -> None:
        self._drop_reader()
        proc, pair, self._proc, self._pair = self._proc, self._pair, None, None
        child.stop(proc, pair, release)


if __name__ == "__main__":
    child.main(serve)
