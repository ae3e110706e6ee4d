"""The station loop and the links on it: their start, stop, status and readiness.

``station-loop`` is an asyncio loop in a thread of its own holding the links (or the station's
side of a link whose server runs in a child process: drivers.links.process), the control
channel and the station's background tasks, so nothing a caller of the station does can
delay a trigger's arrival or its answer.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Callable, Coroutine
from pathlib import Path
from typing import Any

from drivers.links import Link, StationHandler, link_settings, open_links
from drivers.links.base import AlarmNotice
from mvpose_core.station import StationConfig

log = logging.getLogger(__name__)


class LinkHost:
    """Runs the station loop and the station's links on it."""

    def __init__(self) -> None:
        self.links: list[Link] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._tasks: list[asyncio.Task[None]] = []

    @property
    def loop(self) -> asyncio.AbstractEventLoop | None:
        return self._loop

    def start(self, station: StationConfig, handler: StationHandler, answer_margin_s: float,
              data_dir: Path | None,
              tasks: dict[str, Callable[[], Coroutine[Any, Any, None]]]) -> None:
        """Start the loop, then every link the station file enables, then ``tasks`` (by name)
        on the loop; they are cancelled when the links stop."""
        self._loop, self._thread = _loop_thread("station-loop")
        # an OPC UA link's process imports asyncua before it answers (seconds on a loaded host)
        self.run(self._start(station, handler, answer_margin_s, data_dir, tasks), timeout=30)

    async def _start(self, station: StationConfig, handler: StationHandler,
                     margin: float, data_dir: Path | None,
                     tasks: dict[str, Callable[[], Coroutine[Any, Any, None]]]) -> None:
        configs: dict[str, Any] = {}
        for name, cfg in link_settings(station.links).items():  # one block per backend
            if getattr(cfg, "measure_timeout_s", 0) is None:  # a backstop behind the watchdog
                cfg = cfg.model_copy(update={
                    "measure_timeout_s": station.deadline_ms / 1000.0 + margin + 1.0})
            if getattr(cfg, "pki_dir", "") is None and data_dir is not None:
                # certificates (OPC UA) live in the data directory, with the store
                cfg = cfg.model_copy(update={"pki_dir": str(data_dir / name)})
            configs[name] = cfg
        self.links = open_links(configs, handler)
        for link in self.links:
            await link.start()
        self._tasks = [asyncio.create_task(make(), name=name) for name, make in tasks.items()]

    def stop(self) -> None:
        """Stop the tasks and the links, then the loop."""
        if self._loop is None:
            return
        try:
            self.run(self._stop(), timeout=10)
        except Exception:
            log.exception("links did not stop cleanly")
        self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=10)
        self._loop = None

    async def _stop(self) -> None:
        for task in self._tasks:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self._tasks = []
        for link in self.links:
            await link.stop()
        self.links = []

    def run(self, coro: Any, timeout: float | None = None) -> Any:
        """Run a coroutine on the station loop from another thread and wait for its result."""
        if self._loop is None:
            coro.close()
            raise RuntimeError("the station is not running")
        return asyncio.run_coroutine_threadsafe(coro, self._loop).result(timeout)

    def recipe_changed(self) -> None:
        """Every link shows the selected recipe again (a PLC handshake: INITIALIZED -> READY)."""
        if self._loop is None:
            return
        for link in self.links:
            self._loop.call_soon_threadsafe(link.recipe_changed)

    def alarm_changed(self, notice: AlarmNotice) -> None:
        """Every link hears of a station alarm's transition (OPC UA: a condition event)."""
        if self._loop is None:
            return
        for link in self.links:
            self._loop.call_soon_threadsafe(link.alarm_changed, notice)

    # ------------------------------------------------------------------ status
    def link(self, name: str) -> Link | None:
        """The running link of backend ``name`` (a key of drivers.links.BACKENDS), if any."""
        return next((lk for lk in self.links if lk.name == name), None)

    def plc(self) -> Link | None:
        """The link that shows the line's PLC a handshake state (Link.line_state), if any: the
        station status's ``state`` and ``plc`` entries are its."""
        return next((lk for lk in self.links if lk.line_state() is not None), None)

    def ready(self) -> bool:
        return bool(self.links) and all(lk.ready() for lk in self.links)

    def status(self) -> dict[str, dict[str, Any]]:
        return {lk.name: lk.status() for lk in self.links}


def _loop_thread(name: str) -> tuple[asyncio.AbstractEventLoop, threading.Thread]:
    """A new event loop running in a daemon thread of its own (stopped with ``loop.stop``)."""
    loop = asyncio.new_event_loop()

    def main() -> None:
        asyncio.set_event_loop(loop)
        try:
            loop.run_forever()
        finally:
            loop.close()

    thread = threading.Thread(target=main, name=name, daemon=True)
    thread.start()
    return loop, thread
