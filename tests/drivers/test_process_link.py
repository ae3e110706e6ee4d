"""The OPC UA link in a process of its own (drivers.links.process): the station's handler answers
across the socket, results reach the child's clients, a child that dies is started again, a child
whose station dies ends. asyncua's Client is the peer; the handler is the tests' own.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from child_links import hosted_link
from opcua_events import Events
from opcua_handler import PASSWORDS, RecordingHandler, link_config
from waiting import until

from drivers.links import LinkOutcome, LinkRequest, open_links
from drivers.links.opcua import MV_URI, MVPOSE_URI
from drivers.links.process import STOP_S, ProcessLink
from mvpose_core.reasons import Reason

START_S = 120.0  # importing the Machine Vision NodeSet takes seconds on a loaded machine


@pytest_asyncio.fixture
async def hosted(tmp_path: Path) -> AsyncIterator[tuple[ProcessLink, RecordingHandler]]:
    config = link_config(tmp_path / "pki", security=["None"], allow_anonymous=True)
    async with hosted_link({"opcua": config}, START_S) as link_and_handler:
        yield link_and_handler


class Session:
    """An operator's session (security None, as the test's config allows) subscribed to the
    result events."""

    def __init__(self, client: Client, vs: Any, own: int, events: Events) -> None:
        self.client, self.vs, self.own, self.events = client, vs, own, events

    @classmethod
    async def open(cls, link: ProcessLink) -> Session:
        client = Client(f"opc.tcp://127.0.0.1:{link.port}/mvpose", timeout=10,
                        watchdog_intervall=10)
        client.set_user("olga")
        client.set_password(PASSWORDS["olga"])
        await client.connect()
        await client.load_data_type_definitions()
        mv = await client.get_namespace_index(MV_URI)
        own = await client.get_namespace_index(MVPOSE_URI)
        vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
        etype = await client.nodes.base_event_type.get_child(
            [f"{mv}:ResultReadyEventType", f"{own}:MvposeResultReadyEventType"])
        events = Events(timeout_s=10.0)
        sub = await client.create_subscription(50, events)
        await sub.subscribe_events(vs, etype)
        return cls(client, vs, own, events)

    async def measure(self, part: str, trigger: int) -> list[Any]:
        """VisionSystem.Measure: result id, code, offset, 1σ mm, 1σ deg."""
        out: list[Any] = await self.vs.call_method(
            f"{self.own}:Measure", ua.Variant(part, ua.VariantType.String),
            ua.Variant(0, ua.VariantType.UInt16), ua.Variant(trigger, ua.VariantType.UInt32))
        return out

    async def close(self) -> None:
        await self.client.disconnect()


async def test_the_childs_calls_are_answered_by_the_station_processs_handler(
        hosted: tuple[ProcessLink, RecordingHandler]) -> None:
    link, handler = hosted
    pid = link.status()["pid"]
    assert pid not in (0, os.getpid()) and link.ready()
    session = await Session.open(link)
    try:
        rid, code, offset, s_mm, _ = await session.measure("VIN-P1", 61)
        req, out = handler.records[-1]  # this process's handler measured it
        assert (req.link, req.trigger_id, req.part_id) == ("opcua", 61, "VIN-P1")
        assert (rid, code, offset, s_mm) == (out.result_id, 0, list(out.offset), 0.05)
        ev = await session.events.next()
        assert (ev.ResultId.Id, ev.PartId.Id) == (str(rid), "VIN-P1")

        # a result recorded elsewhere (another link; told from a thread of its own)
        other = handler.record(LinkRequest("modbus", 62, 0, None, "VIN-P2", 0),
                               LinkOutcome(int(Reason.MARKS_MISSING), 0), "NOK")
        ev = await session.events.next()
        assert (ev.ResultId.Id, ev.ResultCode) == (str(other.result_id),
                                                   int(Reason.MARKS_MISSING))

        # an exception in the station's handler: recorded across the socket as HANDLER_FAILED
        handler.fail = True
        rid, code, *_ = await session.measure("VIN-P3", 63)
        handler.fail = False
        req, out = handler.records[-1]
        assert (code, rid, req.part_id) == (int(Reason.HANDLER_FAILED), out.result_id, "VIN-P3")
        assert (await session.events.next()).ResultId.Id == str(rid)

        # the selected recipe is the station's, told to the child when it changes
        number = await session.vs.get_child([f"{await session.client.get_namespace_index(MV_URI)}"
                                             ":RecipeManagement", f"{session.own}:ActiveRecipe",
                                             f"{session.own}:Number"])
        assert await number.read_value() == 1
        handler.recipe = 2
        link.recipe_changed()
        deadline = time.monotonic() + 10
        while await number.read_value() != 2:
            assert time.monotonic() < deadline, "the child did not show recipe 2"
            await asyncio.sleep(0.05)
        assert session.events.queue.empty()  # one event per record
    finally:
        await session.close()
    await until(lambda: link.status().get("results_published") == 3, "the child's count")


async def test_the_child_runs_under_the_normal_scheduler_whatever_the_station_runs_under(
        tmp_path: Path) -> None:
    handler = RecordingHandler()
    (link,) = open_links({"opcua": link_config(tmp_path / "pki", security=["None"])}, handler)
    assert isinstance(link, ProcessLink)
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(5))  # as the station's loop runs
    try:
        await link.start()
    finally:
        os.sched_setscheduler(0, *before)
    try:
        pid = link.status()["pid"]
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER
        await until(link.started.is_set, "the child's server listens", START_S)
        tasks = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
        assert {os.sched_getscheduler(t) for t in tasks} == {os.SCHED_OTHER}
    finally:
        await link.stop()
    assert not Path(f"/proc/{pid}").exists()  # reaped


async def test_a_killed_child_is_started_again_and_serves_as_before(
        hosted: tuple[ProcessLink, RecordingHandler]) -> None:
    link, handler = hosted
    first = link.status()["pid"]
    os.kill(first, signal.SIGKILL)
    # the link is down at once; why it ended is known once the child is reaped
    await until(lambda: not link.ready(), "the link is down")
    await until(lambda: "SIGKILL" in (link.status().get("last_exit") or ""),
                "the status names the SIGKILL")
    await until(lambda: link.started.is_set() and link.status()["pid"] != first,
                 "a new child listens", START_S)
    assert link.status()["process_starts"] == 2
    session = await Session.open(link)
    try:
        rid, code, *_ = await session.measure("VIN-AGAIN", 71)
        assert (code, rid) == (0, handler.records[-1][1].result_id)
        assert (await session.events.next()).ResultId.Id == str(rid)
        assert session.events.queue.empty()
    finally:
        await session.close()
    assert len(handler.listeners) == 1  # the station's one listener serves every child


async def test_a_child_whose_station_is_killed_ends(tmp_path: Path) -> None:
    """The station process killed with SIGKILL: its child sees its socket close and stops."""
    script = (
        "import asyncio, sys\n"
        "from pathlib import Path\n"
        "from opcua_handler import RecordingHandler, link_config\n"
        "from drivers.links import open_links\n"
        "async def main():\n"
        f"    cfg = link_config(Path({str(tmp_path / 'pki')!r}), security=['None'])\n"
        "    (link,) = open_links({'opcua': cfg}, RecordingHandler())\n"
        "    await link.start()\n"
        "    print(link.status()['pid'], flush=True)\n"
        "    await asyncio.Event().wait()\n"
        "asyncio.run(main())\n")
    tests = str(Path(__file__).resolve().parents[1])
    station = subprocess.Popen(  # noqa: S603 - our own interpreter
        [sys.executable, "-c", script], stdout=subprocess.PIPE,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([tests, os.getcwd()])})
    try:
        assert station.stdout is not None
        line = await asyncio.wait_for(asyncio.to_thread(station.stdout.readline), START_S)
        child = int(line)
        assert Path(f"/proc/{child}").exists()
    finally:
        station.kill()
        station.wait(30)

    def ended() -> bool:
        try:
            return Path(f"/proc/{child}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
        except FileNotFoundError:
            return True

    await until(ended, "the orphaned child ends", 30.0)


async def test_a_link_that_cannot_start_says_why_and_leaves_no_process(tmp_path: Path) -> None:
    not_a_dir = tmp_path / "pki"
    not_a_dir.write_text("a file where the certificates would go")
    (link,) = open_links({"opcua": link_config(not_a_dir)}, RecordingHandler())
    assert isinstance(link, ProcessLink)
    with pytest.raises(RuntimeError, match=r"opcua link \(process \d+\) did not start: "):
        await link.start()
    pid = link.status()["pid"]
    assert not Path(f"/proc/{pid}").exists()
    assert link.status()["error"] and not link.ready()


async def test_a_child_that_stops_reading_is_killed_before_the_station_buffers_much(
        hosted: tuple[ProcessLink, RecordingHandler]) -> None:
    """A frozen child (SIGSTOP here) reads no results: past the link's backlog limit the station
    kills it rather than keep every result for it, and a new child serves."""
    link, handler = hosted
    link.backlog_limit = 64 * 1024  # the default is 4 MiB; the socket's own buffer comes first
    frozen = link.status()["pid"]
    os.kill(frozen, signal.SIGSTOP)
    part = "P" * 2000  # ~2 KB a result
    for k in range(2000):
        handler.record(LinkRequest("modbus", k, 0, None, part, 0), LinkOutcome(0, 0), "OK")
        await asyncio.sleep(0)  # the listener's hand-over runs on this loop
        if "unread" in (link.status().get("last_exit") or ""):
            break
    await until(lambda: "bytes unread" in (link.status().get("last_exit") or ""),
                "the frozen child killed", 10.0)
    assert "SIGKILL" in link.status()["last_exit"] and not Path(f"/proc/{frozen}").exists()
    await until(lambda: link.started.is_set() and link.status()["pid"] != frozen,
                "a new child listens", START_S)
    session = await Session.open(link)
    try:
        rid, code, *_ = await session.measure("VIN-THAWED", 81)
        assert code == 0 and (await session.events.next()).ResultId.Id == str(rid)
    finally:
        await session.close()


async def test_a_frozen_child_does_not_hold_up_the_stations_stop(tmp_path: Path) -> None:
    """Stopped (SIGSTOP) with results waiting for it beyond the socket's buffer (under the
    backlog limit): the station's stop neither waits for it to read them nor for it to end."""
    handler = RecordingHandler()
    (link,) = open_links({"opcua": link_config(tmp_path / "pki", security=["None"])}, handler)
    assert isinstance(link, ProcessLink)
    await link.start()
    await until(link.started.is_set, "the child's server listens", START_S)
    pid = link.status()["pid"]
    os.kill(pid, signal.SIGSTOP)  # it will read neither the results nor "stop"
    for k in range(400):  # ~800 KB: more than the socket holds, less than the limit
        handler.record(LinkRequest("modbus", k, 0, None, "P" * 2000, 0), LinkOutcome(0, 0), "OK")
        await asyncio.sleep(0)
    assert link.ready()  # not killed: under the backlog limit
    t = time.monotonic()
    await link.stop()
    assert time.monotonic() - t < STOP_S + 1.0  # within a container runtime's 5 s
    assert "SIGKILL" in (link.status().get("last_exit") or "")
    assert not Path(f"/proc/{pid}").exists()
