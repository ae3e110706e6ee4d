"""The station's side of a link in a child process (:class:`ProcessLink`, on the station's loop):
the child started, served, watched and started again; the answers posted by the trigger thread."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import os
import pickle
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

from ..base import AlarmNotice, AnswersEarly, Link, LinkOutcome, StationHandler
from ..result import ResultEvent
from .post import TriggerPost
from .wire import (
    ANSWER_FD,
    BACKLOG_BYTES,
    CALLS,
    CHILD_FD,
    RESTART_S,
    START_S,
    STOP_S,
    Wire,
    portable,
)

log = logging.getLogger(__name__)


class ProcessLink(Link):
    """The station's side of a backend running in a child process (see the module docstring).
    Made per backend by :func:`hosted`; started and stopped on the station's loop."""

    backend: ClassVar[str] = ""
    realtime: ClassVar[bool] = False  # the child keeps the station loop's scheduling policy

    def __init__(self, config: Any, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.pid = 0
        self.starts = 0  # children started
        self.last_exit: str | None = None
        # the child's link says it is ready (also waited on by tests and other threads)
        self.started = threading.Event()
        self._status: dict[str, Any] = {"running": False, "starting": True, "error": None}
        self._line_state: str | None = None  # the child's link's handshake state, if it has one
        self._wire: Wire | None = None
        self._pidfd = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = 0
        self._watch: asyncio.Task[None] | None = None
        self._calls: set[asyncio.Future[Any]] = set()
        self._listening = False
        self.backlog_limit = BACKLOG_BYTES
        self._killed_why = ""  # why this link killed its child, for last_exit
        self._post = TriggerPost()
        # the handler as AnswersEarly, if it is (checked once: a protocol's isinstance is slow)
        self._early = handler if isinstance(handler, AnswersEarly) else None

    # ------------------------------------------------------------------ Link
    async def start(self) -> None:
        """Start the child and its link; raises what the link's start raised there."""
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        await self._spawn()
        self._watch = asyncio.create_task(self._supervise(), name=f"link-{self.name}-process")

    async def stop(self) -> None:
        if self._watch is not None:
            self._watch.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._watch
            self._watch = None
        await self._end_child()
        for call in list(self._calls):
            call.cancel()

    def ready(self) -> bool:
        return self.started.is_set() and self._wire is not None

    def status(self) -> dict[str, Any]:
        return {**self._status, "pid": self.pid, "process_starts": self.starts,
                **({"last_exit": self.last_exit} if self.last_exit else {})}

    @property
    def port(self) -> int:
        """The port the child's link listens on (its status says it)."""
        port = self._status.get("port")
        if not isinstance(port, int):
            raise RuntimeError(f"the {self.name} link is not running")
        return port

    def line_state(self) -> str | None:
        """The child's link's handshake state as its last status report gave it."""
        return self._line_state

    def recipe_changed(self) -> None:
        if self._wire is not None:
            self._send(self._wire, "recipe_changed", self._snapshot())

    def alarm_changed(self, notice: AlarmNotice) -> None:
        if self._wire is not None:
            self._send(self._wire, "alarm", notice.to_dict())

    # ------------------------------------------------------------------ the child
    async def _spawn(self) -> None:
        ours, theirs = socket.socketpair()
        post, posted = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        root = str(Path(__file__).resolve().parents[3])
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            p for p in (root, os.environ.get("PYTHONPATH", "")) if p)}
        argv = [sys.executable, "-m", "drivers.links.process", self.backend]
        actions = [(os.POSIX_SPAWN_DUP2, theirs.fileno(), CHILD_FD),
                   (os.POSIX_SPAWN_DUP2, posted.fileno(), ANSWER_FD)]
        try:
            if self.realtime:  # the policy of this thread: the station loop's
                pid = os.posix_spawn(sys.executable, argv, env, file_actions=actions)
            else:
                pid = os.posix_spawn(sys.executable, argv, env, file_actions=actions,
                                     scheduler=(os.SCHED_OTHER, os.sched_param(0)))
        except BaseException:
            post.close()
            raise
        finally:
            theirs.close()
            posted.close()
        self.pid, self.starts = pid, self.starts + 1
        self._pidfd = os.pidfd_open(pid)
        reader, writer = await asyncio.open_unix_connection(sock=ours)
        wire = self._wire = Wire(reader, writer)  # stop() reaches a child that is starting
        self._post.open(post, lambda message: self._posted(wire, message))
        wire.send("start", self.backend, self.config, logging.getLogger().getEffectiveLevel(),
                  self._snapshot())
        hung = False
        try:
            answer = await asyncio.wait_for(self._until_started(wire), START_S)
        except TimeoutError:
            answer, hung = None, True
        if answer is None or answer[0] != "started" or answer[1] is not None:
            if hung:
                why = f"no answer within {START_S:g} s"
            elif answer is not None and answer[0] == "started":
                why = str(answer[1])
            else:
                why = "the process ended before its link started"
            self._wire = None
            wire.close()
            self._post.close()
            await self._reap(0.0 if hung else STOP_S)
            self._status = {"running": False, "starting": False, "error": why}
            raise RuntimeError(f"the {self.name} link (process {pid}) did not start: {why}")
        log.info("%s link: process %d", self.name, pid)

    async def _supervise(self) -> None:
        """Serve the child until it ends; start it again unless the link is stopping."""
        backoff = RESTART_S[0]
        while True:
            began = time.monotonic()
            assert self._wire is not None
            await self._serve(self._wire)
            self._wire = None
            self._post.close()
            self.started.clear()
            self._line_state = None
            how = await self._reap(STOP_S)
            why, self._killed_why = self._killed_why, ""
            self.last_exit = f"process {self.pid} ended ({how}{'; ' + why if why else ''})"
            if time.monotonic() - began > 60.0:
                backoff = RESTART_S[0]
            while True:
                self._status = {"running": False, "starting": True,
                                "error": f"{self.last_exit}; starting again in {backoff:g} s"}
                log.error("%s link: %s; starting it again in %g s", self.name, self.last_exit,
                          backoff)
                await asyncio.sleep(backoff)
                backoff = min(backoff * 2, RESTART_S[1])
                try:
                    await self._spawn()
                    break
                except Exception as err:  # noqa: BLE001 - shown in the status, tried again
                    self.last_exit = str(err)

    async def _until_started(self, wire: Wire) -> tuple[Any, ...] | None:
        """The child's "started" (None: it ended first), serving its calls meanwhile (a link
        may select its initial recipe while it starts)."""
        while (message := await wire.read()) is not None:
            if message[0] == "started":
                return message
            self._dispatch(wire, message)
        return None

    async def _serve(self, wire: Wire) -> None:
        while (message := await wire.read()) is not None:
            self._dispatch(wire, message)
        wire.close()

    def _dispatch(self, wire: Wire, message: tuple[Any, ...]) -> None:
        kind = message[0]
        if kind == "call":
            self._call(wire, *message[1:])
        elif kind == "status":
            self._status, ready, self._line_state = message[1:4]
            if ready:
                self.started.set()
            else:
                self.started.clear()
        elif kind == "listen" and not self._listening:
            self._listening = True  # once per ProcessLink: a restarted child gets the same
            self.handler.add_listener(self._on_result)

    def _call(self, wire: Wire, call_id: int, method: str, args: tuple[Any, ...]) -> None:
        if method not in CALLS:
            self._send(wire, "reply", call_id, False,
                       ValueError(f"no handler call {method!r}"), self._snapshot())
            return
        posted = threading.Event()  # the outcome went out from the thread that recorded it
        try:
            if method == "measure" and isinstance(self.handler, AnswersEarly):
                call = asyncio.ensure_future(self.handler.measure_early(
                    args[0], self._poster(call_id, posted)))
            else:
                call = asyncio.ensure_future(getattr(self.handler, method)(*args))
        except Exception as err:  # noqa: BLE001 - the child's caller gets it
            self._send(wire, "reply", call_id, False, portable(err), self._snapshot())
            return
        self._calls.add(call)

        def done(f: asyncio.Future[Any]) -> None:
            self._calls.discard(f)
            self._reply(wire, call_id, method, f, posted)

        call.add_done_callback(done)

    def _posted(self, wire: Wire, message: tuple[Any, ...]) -> None:
        """A trigger request the child posted (on the answers' socket's reader thread): started
        from this thread when the handler can (AnswersEarly), else as a call on the loop."""
        _, call_id, request = message
        loop = self._loop
        if loop is None:
            return
        early = self._early
        if early is None:
            loop.call_soon_threadsafe(self._call, wire, call_id, "measure", (request,))
            return
        posted = threading.Event()
        work: concurrent.futures.Future[LinkOutcome]
        try:
            work = early.measure_posted(request, self._poster(call_id, posted))
        except Exception as err:  # noqa: BLE001 - the child's caller gets it
            work = concurrent.futures.Future()
            work.set_exception(err)

        def done(f: concurrent.futures.Future[LinkOutcome]) -> None:
            if f.cancelled() or posted.is_set():
                return  # nothing for the loop to do: the usual case
            with contextlib.suppress(RuntimeError):  # the loop has closed: the station stops
                loop.call_soon_threadsafe(self._reply, wire, call_id, "measure", f, posted)

        work.add_done_callback(done)

    def _poster(self, call_id: int, posted: threading.Event) -> Callable[[LinkOutcome], None]:
        """``answered`` for a trigger: its outcome posted to the child from the recording
        thread (``posted`` set if it went)."""
        def answered(outcome: LinkOutcome) -> None:
            if self._post.send(("reply", call_id, True, outcome, None)):
                posted.set()

        return answered

    def _reply(self, wire: Wire, call_id: int, method: str,
               f: asyncio.Future[Any] | concurrent.futures.Future[Any],
               posted: threading.Event) -> None:
        """The answer to a call that has ended, on the wire (on the loop), unless the thread
        that recorded it posted it already."""
        if f.cancelled() or posted.is_set():
            return
        err = f.exception()
        try:
            if err is None:
                self._send(wire, "reply", call_id, True, f.result(), self._snapshot())
                return
        except (pickle.PicklingError, TypeError, AttributeError) as bad:
            err = RuntimeError(f"{method}: the answer cannot cross to the link's process "
                               f"({type(bad).__name__}: {bad})")
        self._send(wire, "reply", call_id, False, portable(err), self._snapshot())

    def _on_result(self, event: ResultEvent) -> None:
        """The station's listener: hand the result to the child (from any thread)."""
        if threading.get_ident() == self._thread:
            self._forward(event)
        elif self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._forward, event)

    def _forward(self, event: ResultEvent) -> None:
        if self._wire is not None:  # the event's one serialised shape, not a pickle of it
            self._send(self._wire, "result", event.to_json())

    def _send(self, wire: Wire, *message: Any) -> None:
        """Send to the child; a child that has stopped reading (frozen, SIGSTOP) would make the
        station buffer every result for it, so past ``backlog_limit`` unread bytes it is killed
        (and started again, as after any death)."""
        wire.send(*message)
        if wire.closed or wire.backlog() <= self.backlog_limit:
            return
        self._killed_why = f"killed: it left {wire.backlog()} bytes unread"
        log.error("%s link: process %d %s", self.name, self.pid, self._killed_why)
        wire.close()
        with contextlib.suppress(ProcessLookupError):
            os.kill(self.pid, signal.SIGKILL)

    def _snapshot(self) -> tuple[int, Any]:
        return self.handler.selected_recipe(), self.handler.convention()

    async def _end_child(self) -> None:
        wire, self._wire = self._wire, None
        self.started.clear()
        self._line_state = None
        self._post.close()
        deadline = time.monotonic() + STOP_S  # reading "stop" and ending, together
        if wire is not None:
            wire.send("stop")
            with contextlib.suppress(Exception):  # a frozen child reads nothing: bounded
                await asyncio.wait_for(wire.writer.drain(), STOP_S)
        if self._pidfd >= 0:
            code = await self._reap(max(0.0, deadline - time.monotonic()))
            self.last_exit = f"process {self.pid} ended ({code})"
        if wire is not None:
            wire.close()
        self._status = {"running": False, "starting": False, "error": None}

    async def _reap(self, timeout_s: float) -> str:
        """Wait for the child to end (SIGKILL after ``timeout_s``); how it ended."""
        fd, self._pidfd = self._pidfd, -1
        if fd < 0:
            return "already reaped"
        loop = asyncio.get_running_loop()
        ended: asyncio.Future[None] = loop.create_future()

        def readable() -> None:
            if not ended.done():
                ended.set_result(None)

        loop.add_reader(fd, readable)
        try:
            try:
                await asyncio.wait_for(ended, timeout_s)
            except TimeoutError:
                log.error("%s link: process %d did not end within %g s; killing it",
                          self.name, self.pid, timeout_s)
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.pid, signal.SIGKILL)
            _, status = await asyncio.to_thread(os.waitpid, self.pid, 0)
        finally:
            loop.remove_reader(fd)
            os.close(fd)
        if os.WIFSIGNALED(status):
            return f"signal {signal.Signals(os.WTERMSIG(status)).name}"
        return f"exit {os.waitstatus_to_exitcode(status)}"


_HOSTED: dict[str, type[ProcessLink]] = {}


def hosted(backend: str) -> type[ProcessLink]:
    """The ProcessLink class that runs ``backend`` (a key of BACKENDS) in a child process, under
    the backend's name."""
    from .. import REALTIME

    if backend not in _HOSTED:
        _HOSTED[backend] = type(f"{backend.capitalize()}ProcessLink", (ProcessLink,),
                                {"name": backend, "backend": backend,
                                 "realtime": backend in REALTIME})
    return _HOSTED[backend]
