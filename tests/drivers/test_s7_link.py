"""The S7 link on loopback against python-snap7's own server as the PLC (a CPU with the two DBs,
:class:`drivers.links.s7.twin.S7Cpu`), the PLC program being the project's twin on those DBs:
flows, what is written when, bad PLC projects, a PLC that goes and comes back."""

# ruff: noqa: F811

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
import pytest_asyncio
from plc_peers import ArithmeticHandler, expected_outcome
from waiting import until

from drivers.links import link_settings
from drivers.links.layout import INPUT_SIZE, ErrorCode, Status
from drivers.links.s7 import S7Link, S7LinkConfig
from drivers.links.s7.twin import S7Cpu, S7Port
from drivers.links.twin import PlcTwin

LOG = "drivers.links.s7.link"
Factory = Callable[..., Awaitable[tuple[S7Link, PlcTwin]]]


def _config(cpu: S7Cpu, **overrides: Any) -> S7LinkConfig:
    # a watchdog long enough for a loaded machine's stalls; quick reconnects for the tests
    block: dict[str, Any] = {**cpu.settings, "watchdog_s": 10.0, "reconnect_min_s": 0.05,
                             "reconnect_max_s": 0.4, **overrides}
    cfg = link_settings({"s7": block})["s7"]
    assert isinstance(cfg, S7LinkConfig)
    return cfg


@pytest_asyncio.fixture
async def s7() -> AsyncIterator[Factory]:
    """An S7 CPU on a free loopback port, the S7 link connected to it with recipe 1 selected,
    and the twin's program on the CPU; all stopped after the test."""
    cpus: list[S7Cpu] = []
    links: list[S7Link] = []

    async def make(handler: ArithmeticHandler | None = None, cpu: S7Cpu | None = None,
                   connect: bool = True, **overrides: Any) -> tuple[S7Link, PlcTwin]:
        cpu = cpu or S7Cpu()
        cpu.start()
        cpus.append(cpu)
        handler = handler or ArithmeticHandler()
        handler.recipe = 1
        link = S7Link(_config(cpu, **overrides), handler)  # type: ignore[arg-type]
        await link.start()
        links.append(link)
        twin = PlcTwin(S7Port(cpu), poll_s=0.001)
        await twin.connect()
        if connect:
            await until(lambda: link.status()["connected"], "the link connected")
            await twin.enable()
        return link, twin

    yield make
    for link in links:
        await link.stop()
    for cpu in cpus:
        cpu.stop()


async def test_triggers_are_answered_through_the_dbs(s7: Factory) -> None:
    handler = ArithmeticHandler()
    link, twin = await s7(handler)
    for k in (1, 2, 13, 14):
        answer = await twin.cycle(k, part_id=f"VIN{k}", timeout=5.0)
        want = expected_outcome(k)
        assert answer.trigger_id == k and answer.result_code == want.result_code
        assert answer.has(Status.RESULT_OK) == (want.result_code == 0)
        assert answer.result_id == handler.seq
        if want.offset is not None:
            assert answer.offset_float == pytest.approx(want.offset, abs=1e-4)
    assert [r.trigger_id for r in handler.requests] == [1, 2, 13, 14]
    assert [r.link for r in handler.requests] == ["s7"] * 4
    assert handler.requests[0].part_id == "VIN1"
    st = link.status()
    assert st["state"] == "READY" and st["plc_online"] and st["pdu_size"] >= 240


async def test_the_result_block_is_written_only_when_it_changed(s7: Factory) -> None:
    link, twin = await s7()
    await twin.cycle(1, timeout=5.0)
    await until(lambda: link.status()["heartbeat_writes"] >= 1, "a heartbeat write")
    blocks = link.status()["block_writes"]
    beats = link.status()["heartbeat_writes"]
    polls = link.status()["polls"]
    await until(lambda: link.status()["polls"] > polls + 40, "forty polls")
    await until(lambda: link.status()["heartbeat_writes"] > beats + 2, "heartbeat writes")
    st = link.status()
    assert st["block_writes"] == blocks  # nothing but the heartbeat changed: no block written
    assert st["heartbeat_writes"] < st["polls"]  # the heartbeat moves every tick, not every poll
    before = (await twin.read_status()).heartbeat  # ... and it reaches the PLC on its own
    await twin.wait_for(lambda s: s.heartbeat != before, 5.0, "the device heartbeat moving")


@pytest.mark.parametrize(("cpu_kw", "words"), [
    ({"result_db_size": 64}, ("DB101", "64 bytes long", f"{INPUT_SIZE} bytes")),
    ({"trigger_db_size": 0}, ("no DB100", "Optimized block access", "80 bytes")),
    ({"trigger_db_size": 30}, ("DB100", "30 bytes long", "80 bytes")),
    ({"max_pdu": 160}, ("PDU of 160 bytes", "DB101", f"{INPUT_SIZE + 35} bytes")),
])
async def test_a_bad_plc_project_is_named_and_retried_and_nothing_is_measured(
        s7: Factory, caplog: pytest.LogCaptureFixture, cpu_kw: dict[str, Any],
        words: tuple[str, ...]) -> None:
    caplog.set_level(logging.WARNING, LOG)
    handler = ArithmeticHandler()
    cpu = S7Cpu(**cpu_kw)
    link, _twin = await s7(handler, cpu, connect=False)
    await until(lambda: link.status()["block_errors"] >= 3, "three attempts")
    st = link.status()
    assert not st["connected"]
    for word in words:
        assert word in st["problem"], st["problem"]
    assert f"127.0.0.1:{cpu.port}" in st["problem"]  # the PLC
    lines = [r.getMessage() for r in caplog.records if r.name == LOG]
    assert len(lines) == 1, lines  # once per outage, not once per attempt
    assert st["problem"] in lines[0]
    assert handler.requests == [] and handler.seq == 0  # nothing measured, nothing recorded
    if "result_db_size" in cpu_kw:
        assert cpu.read(101, 0, 64) == bytes(64)  # not a byte of the block was written


async def test_a_plc_that_goes_and_comes_back_is_reported_lost_then_resumed(
        s7: Factory, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, LOG)
    handler = ArithmeticHandler()
    link, twin = await s7(handler, watchdog_s=0.5)
    beat = asyncio.create_task(twin.keep_alive(0.05))
    try:
        first = await twin.cycle(1, timeout=5.0)
        cpu = twin.port.cpu  # type: ignore[attr-defined]
        cpu.stop()  # the CPU is gone: refused connections
        await until(lambda: link.line_state() == "ERROR", "the watchdog", 10)
        st = link.status()
        assert not st["connected"] and not st["plc_online"]
        assert st["error_code"] == ErrorCode.WATCHDOG and st["watchdog_trips"] == 1
        attempts = st["outages"]
        await until(lambda: "cannot connect" in link.status()["problem"], "a refused attempt")
        await asyncio.sleep(0)  # noqa: ASYNC110 - one pass; the attempts go on meanwhile
        cpu.start()  # on the same port
        await until(lambda: link.status()["connected"], "connected again", 10, every_s=0.001)
        # Once the link is back, the PLC reads the handshake's block, not the one it held
        # before the outage (READY, no error): a PLC acting on that would reset an error that
        # is still there and trigger into it.
        back = await twin.read_status()  # the CPU's memory, read at once
        assert back.has(Status.ERROR) and not back.has(Status.READY), back
        assert link.status()["outages"] == attempts  # one outage, however many attempts
        await twin.reset_error(5.0)
        again = await twin.cycle(2, timeout=5.0)
        assert again.result_id == first.result_id + 1  # nothing lost, nothing doubled
    finally:
        twin.stop_keep_alive()
        await beat
    warned = [r.getMessage() for r in caplog.records
              if r.name == LOG and r.levelno >= logging.WARNING]
    assert len(warned) == 2, warned  # the outage, and the PLC back
    assert "reachable again" in warned[1]


async def test_an_answer_published_while_the_plc_was_away_arrives_once(s7: Factory) -> None:
    handler = ArithmeticHandler()
    handler.gate = asyncio.Event()
    link, twin = await s7(handler)
    cpu: S7Cpu = twin.port.cpu  # type: ignore[attr-defined]
    before = await twin.read_status()
    await twin.write_trigger(5)
    await until(lambda: len(handler.requests) == 1, "the trigger measured")
    connects = link.status()["connects"]
    cpu.stop()
    await until(lambda: not link.status()["connected"], "the link lost")
    handler.gate.set()  # the answer is published while the PLC is away
    await until(lambda: link.line_state() != "SINGLE_EXECUTION", "the answer published")
    cpu.start()
    await until(lambda: link.status()["connects"] == connects + 1, "connected again", 10)
    answer = await twin.wait_for(lambda s: s.has(Status.RESULT_VALID), 5.0, "the answer")
    assert answer.trigger_id == 5 and answer.result_id == 1 == handler.seq
    assert answer.has(Status.DONE_TOGGLE) != before.has(Status.DONE_TOGGLE)  # toggled once
    assert len(handler.requests) == 1  # TRIGGER still high after the outage: no second edge


async def test_stop_leaves_no_task_and_closes_the_connection(s7: Factory) -> None:
    link, twin = await s7()
    cpu: S7Cpu = twin.port.cpu  # type: ignore[attr-defined]
    await until(lambda: cpu.connections == 1, "one connection")
    await link.stop()
    await until(lambda: cpu.connections == 0, "the connection closed")
    assert link.status() == {"running": False}
