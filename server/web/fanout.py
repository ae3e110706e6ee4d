"""Server-sent events from one watcher to every open stream of this process.

The watcher (a coroutine the feed owns) runs only while someone listens: the first stream starts
it, the last one to close cancels it. A stream ends after :data:`STREAM_S` and the browser's
EventSource opens a new one (``retry``); a browser that cannot keep up loses the oldest message
in its queue, never the watcher's time. The Live page and the camera view are such feeds.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable, Coroutine, Iterable
from dataclasses import dataclass, field
from typing import Any

KEEPALIVE_S = 15.0
STREAM_S = 30.0
#: a browser that cannot keep up loses the oldest message, never the watcher's time
QUEUE = 8


def sse(event: str, data: str) -> str:
    """One server-sent event: its name and its data, a ``data:`` line per line."""
    lines = "".join(f"data: {line}\n" for line in data.splitlines() or [""])
    return f"event: {event}\n{lines}\n"


@dataclass
class Fanout:
    """The streams of one feed and its watcher task (named ``name``)."""

    name: str
    _queues: set[asyncio.Queue[str]] = field(default_factory=set)
    _task: asyncio.Task[None] | None = None

    @property
    def listeners(self) -> int:
        return len(self._queues)

    @property
    def running(self) -> bool:
        return self._task is not None and not self._task.done()

    async def stream(self, watch: Callable[[], Coroutine[Any, Any, None]],
                     first: Callable[[], Iterable[str]]) -> AsyncIterator[str]:
        """Every event for one browser: ``first()`` (the current state), then each one
        published, until :data:`STREAM_S` has passed; ``watch()`` is started if it is not
        running, and cancelled when the last stream ends."""
        queue: asyncio.Queue[str] = asyncio.Queue(QUEUE)
        self._queues.add(queue)
        if not self.running:
            self._task = asyncio.create_task(watch(), name=self.name)
        try:
            yield "retry: 2000\n\n"
            for message in first():
                yield message
            loop = asyncio.get_running_loop()
            end = loop.time() + STREAM_S
            while (left := end - loop.time()) > 0:
                try:
                    yield await asyncio.wait_for(queue.get(), min(KEEPALIVE_S, left))
                except TimeoutError:
                    yield ": keep-alive\n\n"
        finally:
            self._queues.discard(queue)
            if not self._queues and self._task is not None:
                self._task.cancel()  # nobody looks: the watcher stops
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await self._task
                self._task = None

    def publish(self, message: str) -> None:
        """``message`` into every open stream's queue."""
        for q in list(self._queues):
            if q.full():
                with contextlib.suppress(asyncio.QueueEmpty):
                    q.get_nowait()
            q.put_nowait(message)
