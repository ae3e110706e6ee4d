"""A link backend in a process of its own, with the station's :class:`StationHandler` reached
over a socket: the station keeps one GIL for its trigger path.

A backend whose protocol work is pure Python and heavy per result (OPC UA: each result event is
built, deep-copied and encoded by asyncua) or frequent (Modbus/TCP: a PLC polls its status every
few milliseconds) would take the station process's GIL while the trigger thread waits for it.
Listed in ``drivers.links.OWN_PROCESS``, it runs in a child process instead:

- :class:`ProcessLink` stands for it in the station (on the station's loop): it starts the child,
  serves the child's handler calls with the station's handler (also while the child's link
  starts), forwards each result to it, and shows the child's status, readiness and line state.
  A child that dies is started again (backoff 1 s to 30 s); the station and its other links go
  on meanwhile. A child that does not answer its start within ``START_S``, or leaves
  ``BACKLOG_BYTES`` unread (frozen), is killed.
- In the child, ``python -m drivers.links.process <backend>``, the backend runs unchanged against
  :class:`RemoteHandler`, a StationHandler whose calls cross the socket. What the handler answers
  without a call (the selected recipe, its robot convention) comes with every reply and with each
  recipe change.
- A trigger's outcome, from a handler that is :class:`~drivers.links.base.AnswersEarly` (the
  station), is posted to the child by the thread that recorded it, right after the append, on a
  second socket (:class:`_AnswerPost`): the PLC's answer does not wait for the station loop.

The child is started with ``posix_spawn`` under the normal scheduling policy: a station whose
threads run under SCHED_FIFO does not pass its real-time priority on, unless the backend is in
``drivers.links.REALTIME`` (the Modbus link: the PLC's handshake is the trigger path, and its
polls must not wait for the station PC's other work); that child runs at the station loop's
priority. It ends when its socket closes, so a station killed with SIGKILL leaves no child
behind. The socket is a private socketpair between the station and its own child; messages are
pickled frames (length, pickle) of this module's tuples and the seam's dataclasses; a result
event crosses as its own JSON (``ResultEvent.to_json``). This module is the only one that knows
them.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import pickle
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar

from .base import (
    AlarmNotice,
    AnswersEarly,
    HandEyeOutcome,
    Link,
    LinkOutcome,
    LinkRequest,
    StationHandler,
    VerifyOutcome,
)
from .result import ResultEvent

log = logging.getLogger(__name__)

CHILD_FD = 3  # the socket's descriptor in the child
ANSWER_FD = 4  # the answers' socket's descriptor in the child (see _AnswerPost)
STATUS_EVERY_S = 0.2  # the child sends its status when it changed, at most this often
RESTART_S = (1.0, 30.0)  # first and longest wait before a dead child is started again
START_S = 25.0  # a child whose link has not started this long after its spawn is killed
STOP_S = 3.0  # a child that has not read "stop" and ended this long after it is killed
BACKLOG_BYTES = 4 << 20  # a child that leaves this much unread (frozen, stopped) is killed
_HEADER = struct.Struct("!I")
_MAX_FRAME = 64 << 20
# the StationHandler calls a child may make (its answers go back as replies)
CALLS = frozenset({"measure", "record_failure", "select_recipe", "teach_reference", "reset",
                   "verify", "handeye_begin", "handeye_add_pose", "handeye_calculate",
                   "unselect_recipe", "recipes", "get_result", "find_results", "calibrations",
                   "activate_calibration"})


# --------------------------------------------------------------------------- frames
class _Wire:
    """Pickled frames over one stream; writes go out in order on the owning loop."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.closed = False

    def send(self, *message: Any) -> None:
        if self.closed or self.writer.is_closing():
            return
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        self.writer.write(_HEADER.pack(len(data)) + data)

    def backlog(self) -> int:
        """Bytes written that the other side has not read yet (beyond the socket's buffer)."""
        return self.writer.transport.get_write_buffer_size()

    async def read(self) -> tuple[Any, ...] | None:
        """The next message; None when the other side has gone."""
        try:
            (size,) = _HEADER.unpack(await self.reader.readexactly(_HEADER.size))
            if size > _MAX_FRAME:
                raise ValueError(f"a frame of {size} bytes (at most {_MAX_FRAME})")
            message: tuple[Any, ...] = pickle.loads(await self.reader.readexactly(size))
        except (asyncio.IncompleteReadError, ConnectionError):
            return None
        return message

    def close(self) -> None:
        self.closed = True
        self.writer.close()


def _portable(err: BaseException) -> BaseException:
    """``err`` if it survives pickling, else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(err))
    except Exception:  # noqa: BLE001 - any exception a handler raised
        return RuntimeError(f"{type(err).__name__}: {err}")
    return err


# --------------------------------------------------------------------------- station side
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
        self._wire: _Wire | None = None
        self._pidfd = -1
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = 0
        self._watch: asyncio.Task[None] | None = None
        self._calls: set[asyncio.Future[Any]] = set()
        self._listening = False
        self.backlog_limit = BACKLOG_BYTES
        self._killed_why = ""  # why this link killed its child, for last_exit
        self._post = _AnswerPost()

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
        root = str(Path(__file__).resolve().parents[2])
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
        self._post.open(post)
        self.pid, self.starts = pid, self.starts + 1
        self._pidfd = os.pidfd_open(pid)
        reader, writer = await asyncio.open_unix_connection(sock=ours)
        wire = self._wire = _Wire(reader, writer)  # stop() reaches a child that is starting
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

    async def _until_started(self, wire: _Wire) -> tuple[Any, ...] | None:
        """The child's "started" (None: it ended first), serving its calls meanwhile (a link
        may select its initial recipe while it starts)."""
        while (message := await wire.read()) is not None:
            if message[0] == "started":
                return message
            self._dispatch(wire, message)
        return None

    async def _serve(self, wire: _Wire) -> None:
        while (message := await wire.read()) is not None:
            self._dispatch(wire, message)
        wire.close()

    def _dispatch(self, wire: _Wire, message: tuple[Any, ...]) -> None:
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

    def _call(self, wire: _Wire, call_id: int, method: str, args: tuple[Any, ...]) -> None:
        if method not in CALLS:
            self._send(wire, "reply", call_id, False,
                       ValueError(f"no handler call {method!r}"), self._snapshot())
            return
        posted = threading.Event()  # the outcome went out from the thread that recorded it
        try:
            if method == "measure" and isinstance(self.handler, AnswersEarly):
                def answered(outcome: LinkOutcome) -> None:
                    if self._post.send(("reply", call_id, True, outcome, None)):
                        posted.set()

                call = asyncio.ensure_future(self.handler.measure_early(args[0], answered))
            else:
                call = asyncio.ensure_future(getattr(self.handler, method)(*args))
        except Exception as err:  # noqa: BLE001 - the child's caller gets it
            self._send(wire, "reply", call_id, False, _portable(err), self._snapshot())
            return
        self._calls.add(call)

        def done(f: asyncio.Future[Any]) -> None:
            self._calls.discard(f)
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
            self._send(wire, "reply", call_id, False, _portable(err), self._snapshot())

        call.add_done_callback(done)

    def _on_result(self, event: ResultEvent) -> None:
        """The station's listener: hand the result to the child (from any thread)."""
        if threading.get_ident() == self._thread:
            self._forward(event)
        elif self._loop is not None and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self._forward, event)

    def _forward(self, event: ResultEvent) -> None:
        if self._wire is not None:  # the event's one serialised shape, not a pickle of it
            self._send(self._wire, "result", event.to_json())

    def _send(self, wire: _Wire, *message: Any) -> None:
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


class _AnswerPost:
    """The station's side of the answers' socket: a trigger's outcome goes to the child from
    the thread that recorded it (the trigger thread), without waiting for the station loop to
    hear of it first. A SOCK_SEQPACKET socketpair: each send is one whole message or nothing,
    never blocking; a send that fails (the child is not reading: frozen, or gone) leaves the
    reply to the wire, whose backlog rule then deals with the child."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._sock: socket.socket | None = None

    def open(self, sock: socket.socket) -> None:
        sock.setblocking(False)
        with self._lock:
            self._sock = sock

    def send(self, message: tuple[Any, ...]) -> bool:
        try:
            data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001 - the wire's path reports what cannot cross
            return False
        with self._lock:
            if self._sock is None:
                return False
            try:
                self._sock.send(data)
            except OSError:
                return False
        return True

    def close(self) -> None:
        with self._lock:
            sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()


_HOSTED: dict[str, type[ProcessLink]] = {}


def hosted(backend: str) -> type[ProcessLink]:
    """The ProcessLink class that runs ``backend`` (a key of BACKENDS) in a child process, under
    the backend's name."""
    from . import REALTIME

    if backend not in _HOSTED:
        _HOSTED[backend] = type(f"{backend.capitalize()}ProcessLink", (ProcessLink,),
                                {"name": backend, "backend": backend,
                                 "realtime": backend in REALTIME})
    return _HOSTED[backend]


# --------------------------------------------------------------------------- child side
class RemoteHandler:
    """The StationHandler a backend sees in the child: each call crosses the socket."""

    def __init__(self, wire: _Wire, snapshot: tuple[int, Any]) -> None:
        self._wire = wire
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future[Any]] = {}
        self._listeners: list[Callable[[ResultEvent], None]] = []
        self._recipe, self._convention = snapshot
        self._gone = False

    def _ask(self, method: str, *args: Any) -> asyncio.Future[Any]:
        future: asyncio.Future[Any] = asyncio.get_running_loop().create_future()
        if self._gone or self._wire.closed:
            future.set_exception(ConnectionError("the station has gone"))
            return future
        call_id = next(self._ids)
        self._pending[call_id] = future
        future.add_done_callback(lambda _: self._pending.pop(call_id, None))
        self._wire.send("call", call_id, method, args)
        return future

    def answered(self, call_id: int, ok: bool, value: Any,
                 snapshot: tuple[int, Any] | None) -> None:
        """A call's answer; ``snapshot`` None: one posted from a station thread, which carries
        none (it could be older than a recipe change the wire brought)."""
        if snapshot is not None:
            self.snapshot(snapshot)
        future = self._pending.pop(call_id, None)
        if future is None or future.done():
            return  # its caller gave up (a timeout, a client gone)
        if ok:
            future.set_result(value)
        else:
            future.set_exception(value)

    def snapshot(self, snapshot: tuple[int, Any]) -> None:
        self._recipe, self._convention = snapshot

    def gone(self) -> None:
        """The station answers no more: every waiting call and every later one fails."""
        self._gone = True
        for future in list(self._pending.values()):
            if not future.done():
                future.set_exception(ConnectionError("the station has gone"))

    def tell(self, event: ResultEvent) -> None:
        for listen in list(self._listeners):
            try:
                listen(event)
            except Exception:
                log.exception("a result listener failed")

    # ------------------------------------------------------------------ StationHandler
    def measure(self, request: LinkRequest) -> asyncio.Future[LinkOutcome]:
        return self._ask("measure", request)

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        result: int = await self._ask("record_failure", request, code, message, processing_ms)
        return result

    async def select_recipe(self, number: int) -> int:
        result: int = await self._ask("select_recipe", number)
        return result

    async def teach_reference(self, by: str) -> int:
        result: int = await self._ask("teach_reference", by)
        return result

    async def reset(self) -> None:
        await self._ask("reset")

    async def verify(self, link: str, by: str) -> VerifyOutcome:
        result: VerifyOutcome = await self._ask("verify", link, by)
        return result

    async def handeye_begin(self, link: str, by: str, holdout: int | None = None
                            ) -> HandEyeOutcome:
        result: HandEyeOutcome = await self._ask("handeye_begin", link, by, holdout)
        return result

    async def handeye_add_pose(self, link: str, by: str, robot_pose: tuple[float, ...] | None
                               ) -> HandEyeOutcome:
        result: HandEyeOutcome = await self._ask("handeye_add_pose", link, by, robot_pose)
        return result

    async def handeye_calculate(self, link: str, by: str) -> HandEyeOutcome:
        result: HandEyeOutcome = await self._ask("handeye_calculate", link, by)
        return result

    def convention(self) -> Any:
        return self._convention

    def selected_recipe(self) -> int:
        return int(self._recipe)

    async def unselect_recipe(self) -> int:
        result: int = await self._ask("unselect_recipe")
        return result

    async def recipes(self) -> Any:
        return await self._ask("recipes")

    async def get_result(self, result_id: int) -> Any:
        return await self._ask("get_result", result_id)

    async def find_results(self, query: Any) -> Any:
        return await self._ask("find_results", query)

    async def calibrations(self) -> Any:
        return await self._ask("calibrations")

    async def activate_calibration(self, version: int, by: str) -> Any:
        return await self._ask("activate_calibration", version, by)

    def add_listener(self, listen: Callable[[ResultEvent], None]) -> None:
        if not self._listeners:
            self._wire.send("listen")
        self._listeners.append(listen)


async def _child(sock: socket.socket, answers: socket.socket) -> int:
    from . import link_class

    reader, writer = await asyncio.open_unix_connection(sock=sock)
    wire = _Wire(reader, writer)
    first = await wire.read()
    if first is None or first[0] != "start":
        return 2
    _, backend, config, level, snapshot = first
    logging.basicConfig(level=level, stream=sys.stderr,
                        format=f"%(asctime)s %(levelname)s [{backend} link] %(name)s: "
                               "%(message)s")
    handler = RemoteHandler(wire, snapshot)
    link = link_class(backend)(config, handler)
    # One reader: the station's replies answer the handler's calls at once (the link may ask
    # the station while it starts, e.g. for its initial recipe); its other messages wait in
    # order until the link has started. None: the station has gone.
    inbox: asyncio.Queue[tuple[Any, ...] | None] = asyncio.Queue()
    reading = asyncio.create_task(_read(wire, handler, inbox))
    posted = asyncio.create_task(_read_posted(answers, handler))
    try:
        await link.start()
    except Exception as err:  # noqa: BLE001 - the station shows it and raises it
        log.exception("the %s link did not start", backend)
        reading.cancel()
        posted.cancel()
        wire.send("started", f"{type(err).__name__}: {err}")
        await writer.drain()
        return 1
    # its status first: the station knows the link's port and state once start() returns
    shown = (link.status(), link.ready(), link.line_state())
    wire.send("status", *shown)
    wire.send("started", None)
    reporter = asyncio.create_task(_report(wire, link, shown))
    try:
        while (message := await inbox.get()) is not None:
            kind = message[0]
            if kind == "result":
                handler.tell(ResultEvent.from_json(message[1]))
            elif kind == "alarm":
                link.alarm_changed(AlarmNotice.from_dict(message[1]))
            elif kind == "recipe_changed":
                handler.snapshot(message[1])
                link.recipe_changed()
            elif kind == "stop":
                break
    finally:
        reporter.cancel()
        reading.cancel()
        posted.cancel()
        handler.gone()
        await link.stop()
        wire.close()
    return 0


async def _read(wire: _Wire, handler: RemoteHandler,
                inbox: asyncio.Queue[tuple[Any, ...] | None]) -> None:
    """Answer the handler's calls from the station's replies; queue its other messages."""
    while (message := await wire.read()) is not None:
        if message[0] == "reply":
            handler.answered(*message[1:])
        else:
            inbox.put_nowait(message)
    inbox.put_nowait(None)


async def _read_posted(answers: socket.socket, handler: RemoteHandler) -> None:
    """The outcomes the station's threads post (see _AnswerPost), one message per packet."""
    loop = asyncio.get_running_loop()
    while data := await loop.sock_recv(answers, 1 << 16):
        _, call_id, ok, value, snapshot = pickle.loads(data)
        handler.answered(call_id, ok, value, snapshot)


async def _report(wire: _Wire, link: Link, last: Any) -> None:
    """Send the link's status, readiness and line state whenever they changed from ``last``."""
    while True:
        now = (link.status(), link.ready(), link.line_state())
        if now != last:
            wire.send("status", *now)
            last = now
        await asyncio.sleep(STATUS_EVERY_S)


def main() -> int:
    # Ctrl-C in a terminal reaches the whole process group: the station stops this process
    # (a "stop" message, or its socket closing), in order.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    sock = socket.socket(fileno=CHILD_FD)
    answers = socket.socket(fileno=ANSWER_FD)
    answers.setblocking(False)
    return asyncio.run(_child(sock, answers))


if __name__ == "__main__":
    sys.exit(main())
