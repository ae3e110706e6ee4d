"""The child's side of a link in a process of its own: ``python -m drivers.links.process
<backend>`` runs the backend unchanged against :class:`RemoteHandler`, a StationHandler whose
calls cross the socket, and reports the link's status to the station."""

from __future__ import annotations

import asyncio
import gc
import itertools
import logging
import pickle
import signal
import socket
import sys
from collections.abc import Callable
from typing import Any

from ..base import (
    AlarmNotice,
    HandEyeOutcome,
    Link,
    LinkOutcome,
    LinkRequest,
    VerifyOutcome,
)
from ..result import ResultEvent
from .wire import ANSWER_FD, CHILD_FD, STATUS_EVERY_S, Wire

log = logging.getLogger(__name__)


class RemoteHandler:
    """The StationHandler a backend sees in the child: each call crosses the socket."""

    def __init__(self, wire: Wire, snapshot: tuple[int, Any],
                 post: socket.socket | None = None) -> None:
        self._wire = wire
        self._post = post  # the triggers' socket (non-blocking): see _ask
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
        # A trigger goes on the triggers' socket, read by a thread of the station that starts
        # it at once; only when no call is waiting for its answer, so that it never overtakes
        # one (a pipeline reset) still on its way through the station loop.
        posted = method == "measure" and not self._pending and self._posted(call_id, args[0])
        self._pending[call_id] = future
        future.add_done_callback(lambda _: self._pending.pop(call_id, None))
        if not posted:
            self._wire.send("call", call_id, method, args)
        return future

    def _posted(self, call_id: int, request: LinkRequest) -> bool:
        if self._post is None:
            return False
        try:
            self._post.send(pickle.dumps(("measure", call_id, request),
                                         protocol=pickle.HIGHEST_PROTOCOL))
        except OSError:  # full or gone: the wire takes it (and tells whether the station is)
            return False
        return True

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
    from .. import link_class

    reader, writer = await asyncio.open_unix_connection(sock=sock)
    wire = Wire(reader, writer)
    first = await wire.read()
    if first is None or first[0] != "start":
        return 2
    _, backend, config, level, snapshot = first
    logging.basicConfig(level=level, stream=sys.stderr,
                        format=f"%(asctime)s %(levelname)s [{backend} link] %(name)s: "
                               "%(message)s")
    handler = RemoteHandler(wire, snapshot, answers)
    link = link_class(backend)(config, handler)
    # One reader: the station's replies answer the handler's calls at once (the link may ask
    # the station while it starts, e.g. for its initial recipe); its other messages wait in
    # order until the link has started. None: the station has gone.
    inbox: asyncio.Queue[tuple[Any, ...] | None] = asyncio.Queue()
    reading = asyncio.create_task(_read(wire, handler, inbox))
    loop = asyncio.get_running_loop()
    loop.add_reader(answers.fileno(), _read_posted, answers, handler, loop)
    try:
        await link.start()
    except Exception as err:  # noqa: BLE001 - the station shows it and raises it
        log.exception("the %s link did not start", backend)
        reading.cancel()
        loop.remove_reader(answers.fileno())
        wire.send("started", f"{type(err).__name__}: {err}")
        await writer.drain()
        return 1
    # The link's start-up objects out of the garbage collector's oldest generation: its
    # collection traverses them all while the PLC waits (server/station/heap.py says why).
    gc.collect()
    gc.freeze()
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
        loop.remove_reader(answers.fileno())
        handler.gone()
        await link.stop()
        wire.close()
    return 0


async def _read(wire: Wire, handler: RemoteHandler,
                inbox: asyncio.Queue[tuple[Any, ...] | None]) -> None:
    """Answer the handler's calls from the station's replies; queue its other messages."""
    while (message := await wire.read()) is not None:
        if message[0] == "reply":
            handler.answered(*message[1:])
        else:
            inbox.put_nowait(message)
    inbox.put_nowait(None)


def _read_posted(answers: socket.socket, handler: RemoteHandler,
                 loop: asyncio.AbstractEventLoop) -> None:
    """The outcomes the station's threads post (see TriggerPost), one message per packet,
    handed to the handler in the loop pass that finds them readable."""
    while True:
        try:
            data = answers.recv(1 << 16)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:  # the station has gone: the wire says so to the handler
            loop.remove_reader(answers.fileno())
            return
        _, call_id, ok, value, snapshot = pickle.loads(data)
        handler.answered(call_id, ok, value, snapshot)


async def _report(wire: Wire, link: Link, last: Any) -> None:
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
