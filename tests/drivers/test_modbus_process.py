"""The Modbus/TCP link in a process of its own (drivers.links.process; docs/modbus.md, "Its own
process"): the PLC twin polls the child, a trigger crosses to the station's handler and its
answer comes back, the initial recipe is selected through the station while the child starts,
and the handshake's state reaches the station with the child's status. The handler is the
tests' own; the peer is the project's PLC twin over Modbus/TCP.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import pickle
import socket
import threading
from collections.abc import AsyncIterator, Callable

import pytest
import pytest_asyncio
from child_links import hosted_link
from opcua_handler import RecordingHandler
from waiting import until

from drivers.links import LinkOutcome, LinkRequest, open_links
from drivers.links.base import AnswersEarly
from drivers.links.layout import Status
from drivers.links.modbus.settings import ModbusLinkConfig
from drivers.links.process import ProcessLink
from drivers.links.process.child import RemoteHandler
from drivers.links.process.wire import Wire
from server.loopback import attach_twin, detach_twin

START_S = 60.0  # a child imports pymodbus before it listens (seconds on a loaded machine)


@pytest_asyncio.fixture
async def hosted() -> AsyncIterator[tuple[ProcessLink, RecordingHandler]]:
    async with hosted_link({"modbus": ModbusLinkConfig(port=0)}, START_S) as link_and_handler:
        yield link_and_handler


async def test_a_trigger_crosses_to_the_station_and_its_answer_back(
        hosted: tuple[ProcessLink, RecordingHandler]) -> None:
    link, handler = hosted
    # READY needs a recipe: the child selected the station's (a call answered while it started)
    twin, beat = await attach_twin(link.port, 0.001)
    try:
        answer = await twin.cycle(7, 0, timeout=10.0)
        assert answer.trigger_id == 7 and answer.has(Status.RESULT_VALID)
        assert answer.result_code == 0 and answer.has(Status.RESULT_OK)
        ((request, outcome),) = handler.records
        assert (request.link, request.trigger_id, request.recipe) == ("modbus", 7, 1)
        assert answer.result_id == outcome.result_id == 101
        await until(lambda: link.line_state() == "READY", "the line state from the child")
    finally:
        await detach_twin(twin, beat)



class EarlyHandler(RecordingHandler):
    """A station that tells each outcome from a thread of its own (as the trigger thread does
    just after the append) and ends the awaitable only when the test says so."""

    def __init__(self) -> None:
        super().__init__()
        self.release = asyncio.Event()  # ends the awaitables: the loop's way of answering
        self.posted_on: list[str] = []  # the threads measure_posted was called on
        self.unreleased: list[tuple[concurrent.futures.Future[LinkOutcome], LinkOutcome]] = []

    def measure_early(self, request: LinkRequest, answered: Callable[[LinkOutcome], None]
                      ) -> asyncio.Future[LinkOutcome]:
        out = LinkOutcome(0, 0, offset=(1.0, 2.0, 3.0, 0.1, 0.2, 0.3), sigma_trans_mm=0.05,
                          sigma_rot_deg=0.01, processing_ms=5.0)
        recorded = self.record(request, out, "OK")
        threading.Thread(target=answered, args=(recorded,)).start()

        async def later() -> LinkOutcome:
            await self.release.wait()
            return recorded

        return asyncio.ensure_future(later())

    def measure_posted(self, request: LinkRequest, answered: Callable[[LinkOutcome], None]
                       ) -> concurrent.futures.Future[LinkOutcome]:
        """Called on the link's thread that reads the child's trigger requests (not the
        loop): the outcome is posted from a thread of its own; the future ends only when the
        test says so (then nothing more goes to the child)."""
        assert threading.current_thread() is not threading.main_thread()
        self.posted_on.append(threading.current_thread().name)
        out = LinkOutcome(0, 0, offset=(1.0, 2.0, 3.0, 0.1, 0.2, 0.3), sigma_trans_mm=0.05,
                          sigma_rot_deg=0.01, processing_ms=5.0)
        recorded = self.record(request, out, "OK")
        threading.Thread(target=answered, args=(recorded,)).start()
        done: concurrent.futures.Future[LinkOutcome] = concurrent.futures.Future()
        self.unreleased.append((done, recorded))
        return done


async def test_a_trigger_starts_off_the_loop_and_its_outcome_reaches_the_plc_first() -> None:
    """The child posts a trigger to a thread of the station's link, which starts it without the
    station loop (AnswersEarly.measure_posted); the recording thread posts the outcome back at
    once: the PLC has it while the station's future has not ended, and gets it once."""
    handler = EarlyHandler()
    (link,) = open_links({"modbus": ModbusLinkConfig(port=0)}, handler)
    assert isinstance(handler, AnswersEarly)
    await link.start()
    try:
        twin, beat = await attach_twin(link.port, 0.001)
        try:
            answer = await twin.cycle(8, 0, timeout=10.0)
            assert answer.trigger_id == 8 and answer.has(Status.RESULT_VALID)
            assert answer.result_id == 101
            assert handler.posted_on == ["link-triggers"]
            ((done, recorded),) = handler.unreleased
            assert not done.done()
            done.set_result(recorded)  # the station's future ends now: nothing more is sent
            answer = await twin.cycle(9, 0, timeout=10.0)
            assert (answer.trigger_id, answer.result_id) == (9, 102)
            assert handler.posted_on == ["link-triggers"] * 2
        finally:
            await detach_twin(twin, beat)
    finally:
        for done, recorded in handler.unreleased:
            if not done.done():
                done.set_result(recorded)
        handler.release.set()
        await link.stop()


async def test_a_trigger_takes_the_wire_while_a_call_waits_for_its_answer() -> None:
    """The child posts a trigger on the triggers' socket only when none of its calls waits for
    an answer: one that still does (a pipeline reset on its way through the station loop) is
    never overtaken, the trigger follows it on the wire."""
    ours, theirs = socket.socketpair()
    post, posted = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    post.setblocking(False)
    posted.setblocking(False)
    reader, writer = await asyncio.open_unix_connection(sock=ours)
    station_reader, station_writer = await asyncio.open_unix_connection(sock=theirs)
    handler = RemoteHandler(Wire(reader, writer), (1, None), post)
    station = Wire(station_reader, station_writer)
    try:
        request = LinkRequest("modbus", 5, 0, None, "", 0)
        first = handler.measure(request)  # nothing waits: the triggers' socket
        kind, call_id, sent = pickle.loads(posted.recv(1 << 16))
        assert (kind, sent) == ("measure", request)
        handler.answered(call_id, True, LinkOutcome(0, 7), None)
        assert (await first).result_id == 7
        reset = asyncio.ensure_future(handler.reset())  # a call that waits for its answer
        await asyncio.sleep(0)  # one loop pass: the reset's call goes out
        second = handler.measure(LinkRequest("modbus", 6, 0, None, "", 0))
        calls = [await station.read(), await station.read()]
        assert [(c[0], c[2]) for c in calls if c is not None] == [("call", "reset"),
                                                                  ("call", "measure")]
        with pytest.raises(BlockingIOError):  # nothing went past the waiting call
            posted.recv(1 << 16)
        handler.answered(calls[0][1], True, None, (1, None))
        handler.answered(calls[1][1], True, LinkOutcome(0, 8), (1, None))
        await reset
        assert (await second).result_id == 8
    finally:
        handler.gone()
        station.close()
        writer.close()
        post.close()
        posted.close()
