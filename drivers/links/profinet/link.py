"""The PROFINET backend of the link seam: :class:`ProfinetLink`. The IO-device runs in a child
process (:mod:`.transport`); the handshake (:class:`~drivers.links.handshake.HandshakeRunner`)
stays on the station's loop and exchanges whole images with it: the controller's output image
in, the input image out whenever it changed. Every value is big-endian, as PROFINET carries it.

A controller that stops sending (the data hold time) aborts the AR in the child; the outputs
read as zeros and no heartbeat arrives, so the station reports it as it reports a lost PLC
(the handshake's watchdog, ``line_state``).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import subprocess
import time
from typing import Any

from .. import layout as r
from ..base import AlarmNotice, StationHandler
from ..handshake import HandshakeLink, HandshakeRunner
from ..layout import ByteOrder
from . import child
from .alarms import ERROR_CAMERA_DOWN, ERROR_STATION_DOWN
from .settings import ProfinetLinkConfig

log = logging.getLogger(__name__)
START_S = 10.0
RESTART_S = (1.0, 30.0)  # first and longest wait before a dead device process starts again
DIAGNOSED = frozenset({"CAMERA_DOWN", "STATION_DOWN"})  # station alarm codes (docs/alarms.md)


class ProfinetError(RuntimeError):
    """The device's process could not start (names why: no raw sockets, no interface)."""


class ProfinetLink(HandshakeLink):
    """PROFINET IO-device for the line's IO-controller."""

    name = "profinet"
    config: ProfinetLinkConfig

    def __init__(self, config: ProfinetLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self._proc: subprocess.Popen[bytes] | None = None
        self._pair: socket.socket | None = None
        self._poller: asyncio.Task[None] | None = None
        self._sent: bytes = b""
        self._started: asyncio.Future[dict[str, Any]] | None = None
        self.child_stats: dict[str, Any] = {}
        self.stats_at = 0.0  # when the device's last stats came (monotonic)
        self.events: list[dict[str, Any]] = []  # the device's last 20 events
        self._restart: asyncio.Task[None] | None = None
        self.restarts = 0

    async def start(self) -> None:
        cfg = self.config
        runner = HandshakeRunner(self.handler, cfg.handshake(self.handler.selected_recipe()),
                                 link="profinet")
        await runner.start()
        self.runner = runner
        runner.on_change = self._push  # the answer goes to the device as it is published
        try:
            await self._spawn()
        except BaseException:
            await self.stop()
            raise
        self._poller = asyncio.create_task(self._poll(), name="profinet-input")

    async def _spawn(self) -> None:
        """Start the device's process and wait for its start (ProfinetError names why not)."""
        self._proc, ours = child.spawn("drivers.links.profinet.transport", self.config.child())
        self._pair, self._sent = ours, b""
        loop = asyncio.get_running_loop()
        self._started = loop.create_future()
        loop.add_reader(ours.fileno(), self._read)
        started = await asyncio.wait_for(asyncio.shield(self._started), START_S)
        if started["kind"] == "error":
            raise ProfinetError(started["text"])
        log.info("profinet link: %s", started["text"])

    async def _close_child(self) -> None:
        if self._pair is not None:
            asyncio.get_running_loop().remove_reader(self._pair.fileno())
        proc, pair, self._proc, self._pair = self._proc, self._pair, None, None
        if proc is not None or pair is not None:
            await asyncio.to_thread(child.stop, proc, pair)

    async def _respawn(self) -> None:
        """The device's process ended: start it again, waiting 1 s, then up to 30 s."""
        wait = RESTART_S[0]
        while True:
            await self._close_child()
            await asyncio.sleep(wait)
            try:
                await self._spawn()
            except (OSError, ProfinetError, TimeoutError) as err:
                if self.runner is not None:
                    self.runner.note(f"the PROFINET device did not start again: {err}")
                wait = min(2 * wait, RESTART_S[1])
            else:
                self.restarts += 1
                return

    async def _respawn_then_clear(self) -> None:
        try:
            await self._respawn()
        finally:
            self._restart = None

    async def stop(self) -> None:
        for task in (self._poller, self._restart):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._poller = self._restart = None
        await self._close_child()
        if self.runner is not None:
            await self.runner.stop()
            self.runner = None

    # ------------------------------------------------------------------ the child

    def _read(self) -> None:
        assert self._pair is not None
        messages, ended = child.received(self._pair)
        for kind, body in messages:
            if kind == b"O" and self.runner is not None:
                self.runner.write_output(body, ByteOrder.BIG)
                self._push()
            elif kind == b"E":
                event = json.loads(body)
                if self._started is not None and not self._started.done():
                    self._started.set_result(event)
                    continue
                self.events = [*self.events[-19:], event]
                if event["kind"] in ("data_hold_expired", "aborted") and self.runner:
                    self.runner.note(event["text"])
                else:
                    log.info("profinet link: %s", event["text"])
            elif kind == b"S":
                self.child_stats = json.loads(body)
                self.stats_at = time.monotonic()
        if ended:
            asyncio.get_running_loop().remove_reader(self._pair.fileno())
            if self._started is not None and not self._started.done():
                self._started.set_result({"kind": "error",
                                          "text": "the PROFINET device process ended"})
            elif self.runner is not None and self._restart is None:
                self.runner.note("the PROFINET device process ended; starting it again")
                self._restart = asyncio.create_task(self._respawn_then_clear(),
                                                    name="profinet-restart")

    def _push(self) -> None:
        if self.runner is None or self._pair is None:
            return
        image = self.runner.input_image(ByteOrder.BIG)
        if image != self._sent:
            with contextlib.suppress(BlockingIOError):
                self._pair.send(b"I" + image)
                self._sent = image

    async def _poll(self) -> None:
        while True:
            self._push()
            await asyncio.sleep(self.config.poll_s)

    def diagnosis(self, source: str, appears: bool) -> None:
        """A camera (``camera:<id>``) or the station (``station``) went down (``appears``) or
        came back: the device sends the controller a diagnosis alarm on the result
        submodule."""
        if self._pair is None:
            return
        error_type = ERROR_STATION_DOWN if source == "station" else ERROR_CAMERA_DOWN
        with contextlib.suppress(BlockingIOError):
            self._pair.send(b"A" + json.dumps({"source": source, "appears": appears,
                                               "error_type": error_type}).encode())

    def alarm_changed(self, notice: AlarmNotice) -> None:
        """The station's alarms (docs/alarms.md): CAMERA_DOWN and STATION_DOWN become
        diagnosis alarms, appearing when raised and disappearing when cleared."""
        if notice.code in DIAGNOSED and notice.event in ("raised", "cleared"):
            self.diagnosis(notice.source, notice.event == "raised")

    # ------------------------------------------------------------------ the seam

    def ready(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def status(self) -> dict[str, Any]:
        if self.runner is None or not self.ready():
            return {"running": False}
        hs = self.runner.machine.stats
        image = self.runner.machine.image
        st = self.child_stats
        return {
            "running": True, "interface": self.config.interface,
            "station_name": st.get("station_name", self.config.station_name),
            "state": self.runner.machine.state.name, "ar": st.get("ar"),
            "connects": st.get("connects", 0), "releases": st.get("releases", 0),
            "data_hold_expired": st.get("data_hold_expired", 0),
            "malformed": st.get("malformed", 0), "module_diffs": st.get("module_diffs", 0),
            "refused_connects": st.get("refused_connects", 0), "restarts": self.restarts,
            # the input frames' interval: p50 and p99 − p50 over the last 2000 (ms)
            "cycle_p50_ms": st.get("cycle_p50_ms"), "cycle_jitter_ms": st.get("cycle_jitter_ms"),
            "scheduling": st.get("scheduling"),
            "handler_errors": self.runner.stats.handler_errors,
            "last_errors": [*st.get("last_errors", []), *self.runner.stats.last_errors][-5:],
            "server_heartbeat": image[r.IR_HEARTBEAT],
            "plc_online": bool(image[r.IR_STATUS] & r.Status.ONLINE),
            "error_code": image[r.IR_ERROR_CODE],
            "result_id": self.runner.machine.result_id,
            "watchdog_trips": hs.watchdog_trips,
            "missed_triggers": hs.missed_triggers,
        }

