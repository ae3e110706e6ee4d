"""`mvpose serve`: the station process and the API process, started and kept running.

Each child is ``python -m server.cli station|api`` with the options it needs and this process's
environment. A child that dies is started again (after 0.5 s, doubling to 10 s while it keeps
dying young); the other carries on: triggers go on while the API restarts, history is served
while the station restarts (its readiness then says ``station: false``). A child that fails
before it was ever ready is a start-up error: everything stops and ``mvpose serve`` exits with
its code. SIGTERM or SIGINT stops both (SIGTERM, then SIGKILL after ``stop_s``).
"""

from __future__ import annotations

import logging
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

log = logging.getLogger(__name__)


@dataclass
class Child:
    name: str
    argv: list[str]
    ready: Callable[[], bool]  # True once the child serves (control socket, HTTP)
    proc: subprocess.Popen[bytes] | None = None
    started_at: float = 0.0
    was_ready: bool = False  # ever: a child that dies before it is a start-up error
    up: bool = False  # ready since its last start
    restarts: int = 0
    backoff_s: float = 0.5
    history: list[tuple[float, int]] = field(default_factory=list)  # (time, exit code)
    # told when the child ends (False, its exit code) and when it is ready (True, None); called
    # on the supervisor's thread: hand slow work (a database write) to a thread of its own
    on_change: Callable[[bool, int | None], None] | None = None


class Supervisor:
    def __init__(self, children: list[Child], stop_s: float = 4.0) -> None:
        self.children = children
        self.stop_s = stop_s
        self.stopping = threading.Event()

    def _spawn(self, child: Child) -> None:
        child.proc = subprocess.Popen(child.argv)  # noqa: S603 - our own interpreter and module
        child.started_at = time.monotonic()
        log.info("%s process started (pid %d)", child.name, child.proc.pid)

    def run(self) -> int:
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: self.stopping.set())
        for child in self.children:
            self._spawn(child)
        code = 0
        try:
            while not self.stopping.wait(0.1):
                for child in self.children:
                    code = self._watch(child)
                    if code:
                        return code
        finally:
            self._stop_all()
        return code

    def _watch(self, child: Child) -> int:
        assert child.proc is not None
        rc = child.proc.poll()
        if rc is None:
            if not child.up and child.ready():
                child.was_ready = child.up = True
                log.info("%s process ready (pid %d)", child.name, child.proc.pid)
                self._tell(child, True, None)
            return 0
        child.history.append((time.time(), rc))
        if child.up:
            child.up = False
            self._tell(child, False, rc)
        if not child.was_ready:
            print(f"mvpose serve: the {child.name} process stopped with exit code {rc} before "
                  f"it was ready (its error is above)", file=sys.stderr, flush=True)
            return rc or 1
        lived = time.monotonic() - child.started_at
        child.backoff_s = 0.5 if lived > 30 else min(10.0, child.backoff_s * 2)
        print(f"mvpose serve: the {child.name} process (pid {child.proc.pid}) ended with exit "
              f"code {rc} after {lived:.1f} s; starting it again in {child.backoff_s:g} s",
              file=sys.stderr, flush=True)
        if self.stopping.wait(child.backoff_s):
            return 0
        child.restarts += 1
        self._spawn(child)
        return 0

    @staticmethod
    def _tell(child: Child, up: bool, rc: int | None) -> None:
        if child.on_change is None:
            return
        try:
            child.on_change(up, rc)
        except Exception:
            log.exception("%s process: its watcher failed", child.name)

    def _stop_all(self) -> None:
        running = [c.proc for c in self.children if c.proc is not None and c.proc.poll() is None]
        for proc in running:
            proc.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + self.stop_s
        for proc in running:
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("pid %d did not stop within %.0f s: killed", proc.pid, self.stop_s)
                proc.kill()
                proc.wait()


def python_argv(command: str, args: list[str]) -> list[str]:
    return [sys.executable, "-m", "server.cli", command, *args]


