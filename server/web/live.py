"""The Live page's server-sent events: one watcher per process and language, fanned out to every
browser that reads the page in that language.

The watcher asks the store for its newest record (one cheap query every
:data:`POLL_S`) and the station for its status; when either changes it renders the HTML once and
puts it in every subscriber's queue. Browsers never poll: each holds one EventSource. The
watcher runs only while someone listens (:mod:`server.web.fanout`). A stream ends after
:data:`~server.web.fanout.STREAM_S` and the browser reconnects on its own: uvicorn's shutdown
waits for open responses (unless its ``timeout_graceful_shutdown`` is set), so an open Live page
delays a shutdown by at most that.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import anyio.to_thread

from server.web.fanout import Fanout, sse
from server.web.reader import Reader

POLL_S = 0.25
#: how long the newest record's frames are waited for (the archive writes them after the record)
FRAMES_WAIT_S = 15.0
STATUS_EVERY_S = 1.0
@dataclass
class Snapshot:
    newest_id: int | None = None
    result_html: str = ""
    frames_html: str = ""
    status_html: str = ""


@dataclass
class LiveFeed:
    """Fan-out of rendered Live fragments; ``render_result`` / ``render_status`` are blocking
    (they read the store and the station) and run in worker threads."""

    reader: Reader
    render_result: Callable[[Reader, int | None, int | None],
                            tuple[str, str, int | None, bool]]
    render_status: Callable[[], str]
    snapshot: Snapshot = field(default_factory=Snapshot)
    fan: Fanout = field(default_factory=lambda: Fanout("web-live-watcher"))
    _frames_id: int | None = None
    _awaited: int | None = None  # newest record, while its frames may still be being written
    _until: float = 0.0
    polls: int = 0

    @property
    def listeners(self) -> int:
        return self.fan.listeners

    @property
    def running(self) -> bool:
        return self.fan.running

    def stream(self) -> AsyncIterator[str]:
        """Every event for one browser: the current state first, then each change."""
        return self.fan.stream(self._watch, self._current)

    def _current(self) -> list[str]:
        snap = self.snapshot
        out = [sse("status", snap.status_html)] if snap.status_html else []
        if snap.result_html:
            out += [sse("result", snap.result_html), sse("frames", snap.frames_html)]
        return out

    def _publish(self, message: str) -> None:
        self.fan.publish(message)

    async def _watch(self) -> None:
        loop = asyncio.get_running_loop()
        next_status = 0.0
        while True:
            self.polls += 1
            newest = await anyio.to_thread.run_sync(self.reader.newest_id)
            # A record's frames are written after the record (after the PLC has its answer),
            # one camera after another: a newest record whose planned frames are not all on
            # disk yet is looked at again a while.
            waiting = newest is not None and newest == self._awaited and loop.time() < self._until
            if newest != self.snapshot.newest_id or waiting:
                result, frames, frames_id, complete = await anyio.to_thread.run_sync(
                    self.render_result, self.reader, newest, self._frames_id)
                if newest != self.snapshot.newest_id:
                    self._until = loop.time() + FRAMES_WAIT_S
                self._awaited = None if complete else newest
                self._frames_id = frames_id
                self.snapshot.newest_id = newest
                if result != self.snapshot.result_html:
                    self.snapshot.result_html = result
                    self._publish(sse("result", result))
                if frames != self.snapshot.frames_html:
                    self.snapshot.frames_html = frames
                    self._publish(sse("frames", frames))
            if loop.time() >= next_status:
                next_status = loop.time() + STATUS_EVERY_S
                status = await anyio.to_thread.run_sync(self.render_status)
                if status != self.snapshot.status_html:
                    self.snapshot.status_html = status
                    self._publish(sse("status", status))
            await asyncio.sleep(POLL_S)


@dataclass
class LiveFeeds:
    """One :class:`LiveFeed` per language the page is open in (each renders its fragments once
    in its language; a language nobody reads has no watcher)."""

    make: Callable[[str], LiveFeed]
    feeds: dict[str, LiveFeed] = field(default_factory=dict)

    def of(self, code: str) -> LiveFeed:
        if code not in self.feeds:
            self.feeds[code] = self.make(code)
        return self.feeds[code]

    @property
    def listeners(self) -> int:
        return sum(f.listeners for f in self.feeds.values())


def live_of(app: Any) -> LiveFeeds:
    feeds: LiveFeeds = app.state.web_live
    return feeds
