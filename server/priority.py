"""Triggers first: HTTP requests that arrive while a trigger runs wait for it to finish.

The trigger pipeline and the REST API share one process, so one GIL and the same cores: a MES
page request handled during a trigger takes its CPU from detection (docs/performance.md). The
MES polls and can wait a few tens of milliseconds; the PLC cannot. So the runtime marks every
trigger as it starts and ends (:meth:`TriggerFirst.begin` / :meth:`TriggerFirst.end`, from any
thread), and :class:`TriggerFirstMiddleware` holds each new HTTP request until no trigger runs —
at most ``max_wait_s``, so the API never starves on a station triggering back to back. A request
already being handled when a trigger starts is not interrupted. The middleware never holds the
liveness probe.

The HTTP server's event loop itself also sleeps while a trigger runs (``hold_loop``): a callback
scheduled on it at :meth:`TriggerFirst.begin` blocks the loop thread, with the GIL released,
until the trigger ends or ``max_wait_s`` passes. Without it, requests already inside the
framework (parsing, routing, dependencies, sending) keep taking the GIL from the trigger thread
each time detection releases it for an OpenCV call. Everything on that loop, the liveness probe
included, answers up to one trigger (at most ``max_wait_s``) later; the PLC link has a loop of
its own and is never held.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import threading
import time
from collections.abc import Callable

from starlette.types import ASGIApp, Receive, Scope, Send


class TriggerFirst:
    """Counts running triggers; lets coroutines on one event loop wait until none runs."""

    def __init__(self, max_wait_s: float = 0.1, hold_loop: bool = True) -> None:
        if not max_wait_s >= 0:
            raise ValueError(f"max_wait_s must be >= 0, got {max_wait_s}")
        self.max_wait_s = max_wait_s
        self.hold_loop = hold_loop
        self.waiting = 0  # requests held right now (read by tests and the status page)
        self.holding = 0  # 1 while the HTTP loop sleeps in a hold (read by tests)
        self.held = 0  # requests that had to wait, since start
        self._running = 0
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._idle: asyncio.Event | None = None
        self._idle_thread = threading.Event()  # the same state, for threadpool code
        self._idle_thread.set()

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Attach to the HTTP server's event loop (call from that loop, e.g. in the lifespan)."""
        with self._lock:
            self._loop = loop
            self._idle = asyncio.Event()
            if self._running == 0:
                self._idle.set()

    def begin(self) -> None:
        """A trigger starts (any thread)."""
        with self._lock:
            self._running += 1
            if self._running == 1:
                self._idle_thread.clear()
                self._signal(False)

    def end(self) -> None:
        """That trigger is done, whatever its outcome (any thread)."""
        with self._lock:
            self._running = max(0, self._running - 1)
            if self._running == 0:
                self._idle_thread.set()
                self._signal(True)

    @property
    def busy(self) -> bool:
        return self._running > 0

    def _signal(self, idle: bool) -> None:
        # Under the lock: the loop runs these callbacks in the order they were scheduled, so the
        # event ends in the state of the last begin/end.
        loop, event = self._loop, self._idle
        if loop is None or event is None or loop.is_closed():
            return
        loop.call_soon_threadsafe(event.set if idle else event.clear)
        if not idle and self.hold_loop and self.max_wait_s > 0:
            loop.call_soon_threadsafe(self._hold)

    def _hold(self) -> None:
        """On the HTTP loop: sleep until no trigger runs, at most ``max_wait_s`` (module doc)."""
        if not self._idle_thread.is_set():
            self.holding += 1
            try:
                self._idle_thread.wait(self.max_wait_s)
            finally:
                self.holding -= 1

    async def wait(self) -> None:
        """Return when no trigger runs, or after ``max_wait_s`` at most."""
        event = self._idle
        if event is None or event.is_set() or self.max_wait_s == 0:
            return
        self.waiting += 1
        self.held += 1
        try:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(event.wait(), self.max_wait_s)
        finally:
            self.waiting -= 1


    def wait_in_thread(self, timeout_s: float | None = None) -> None:
        """:meth:`wait` for code in a worker thread (FastAPI's threadpool): a request already
        past the middleware when a trigger started waits here before its database work.
        At most ``timeout_s`` (default and upper bound: ``max_wait_s``)."""
        limit = self.max_wait_s if timeout_s is None else min(timeout_s, self.max_wait_s)
        if limit > 0 and not self._idle_thread.is_set():
            self.held += 1
            self._idle_thread.wait(limit)

    def budget(self) -> Callable[[], None]:
        """A checkpoint for one request's long work in a worker thread: each call waits as
        :meth:`wait_in_thread`, all calls together at most ``max_wait_s`` (a 1000-row page
        with a checkpoint every 10 rows must not wait 100 times on a busy station)."""
        left = [self.max_wait_s]

        def pause() -> None:
            if left[0] <= 0 or self._idle_thread.is_set():
                return
            t = time.monotonic()
            self.wait_in_thread(left[0])
            left[0] -= time.monotonic() - t

        return pause


class CollectorPause:
    """Python's cyclic garbage collector waits while a trigger runs.

    A collection stops every thread of the process: measured on station 1's server, a young
    collection took up to 4.5 ms, a middle one 1.5-3 ms and a full one 67-100 ms (a PLC deadline
    is 50 ms). :meth:`freeze` (after start-up) moves every object alive then out of the
    collector's sight, so later full collections only walk what was allocated since;
    :meth:`begin` / :meth:`end` (nested, any thread) switch automatic collection off for the
    duration of a trigger. What the trigger allocated is collected at the next collection after
    it, between triggers; reference counting frees everything else at once as usual.

    The collector is one per process: pauses of every instance (several runtimes in one test
    process) are counted together, and automatic collection resumes when the last one ends.
    """

    _lock = threading.Lock()
    _running = 0  # pauses in progress, all instances
    _resume = False  # whether collection was on when the first pause began

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled
        self._mine = 0  # pauses of this instance in progress (ended by close())
        self._frozen = False

    def freeze(self) -> None:
        """Collect once, then exempt everything alive from later collections (start-up)."""
        if self.enabled:
            gc.collect()
            gc.freeze()
            self._frozen = True

    def begin(self) -> None:
        if not self.enabled:
            return
        cls = CollectorPause
        with cls._lock:
            if cls._running == 0:
                cls._resume = gc.isenabled()
                gc.disable()
            cls._running += 1
            self._mine += 1

    def end(self) -> None:
        if not self.enabled:
            return
        cls = CollectorPause
        with cls._lock:
            if self._mine == 0:
                return  # already ended by close()
            self._mine -= 1
            cls._running -= 1
            if cls._running == 0 and cls._resume:
                gc.enable()

    def close(self) -> None:
        """End this instance's pauses still in progress (a stop during a trigger) and give the
        frozen objects back to the collector."""
        while self._mine:
            self.end()
        if self._frozen:
            gc.unfreeze()
            self._frozen = False

    @property
    def paused(self) -> bool:
        return self._mine > 0


class TriggerFirstMiddleware:
    """ASGI: every HTTP request but the ``exempt`` paths first awaits :meth:`TriggerFirst.wait`."""

    def __init__(self, app: ASGIApp, gate: TriggerFirst, exempt: frozenset[str]) -> None:
        self.app = app
        self.gate = gate
        self.exempt = exempt

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope.get("path") not in self.exempt:
            await self.gate.wait()
        await self.app(scope, receive, send)
