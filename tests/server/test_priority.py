"""Triggers first: HTTP requests, and the HTTP loop itself, wait for a running trigger, bounded."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import numpy as np
import pytest
from stations import ENGINEER, relaxed_deadline, runtime_options, settings_for, station_file

from server.loopback import move_part, running_station, trigger
from server.priority import CollectorPause, TriggerFirst

pytestmark = pytest.mark.timeout(120)


async def until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached before the deadline"
        await asyncio.sleep(0.002)


# The tests of the request-level waiting bind the gate to the test's own loop and drive it from
# there: the loop hold is off for them (it would stop the test itself); it has tests of its own.


async def test_a_waiting_request_goes_on_only_after_the_trigger_ends() -> None:
    gate = TriggerFirst(max_wait_s=10.0, hold_loop=False)
    gate.bind(asyncio.get_running_loop())
    await asyncio.wait_for(gate.wait(), 1.0)  # idle: no wait
    assert gate.held == 0
    await asyncio.to_thread(gate.begin)  # triggers start on other threads
    order: list[str] = []

    async def request() -> None:
        await gate.wait()
        order.append("request went on")

    waiter = asyncio.create_task(request())
    await until(lambda: gate.waiting == 1)
    assert not waiter.done() and gate.busy

    def finish() -> None:
        order.append("trigger ended")
        gate.end()

    await asyncio.to_thread(finish)
    await asyncio.wait_for(waiter, 5.0)
    assert order == ["trigger ended", "request went on"]
    assert gate.held == 1 and gate.waiting == 0 and not gate.busy


async def test_overlapping_triggers_keep_requests_waiting_until_the_last_ends() -> None:
    gate = TriggerFirst(max_wait_s=10.0, hold_loop=False)
    gate.bind(asyncio.get_running_loop())
    gate.begin()
    gate.begin()
    waiter = asyncio.create_task(gate.wait())
    await until(lambda: gate.waiting == 1)
    await asyncio.to_thread(gate.end)  # one of two ended: nothing is signalled yet
    assert gate.busy and not waiter.done()
    await asyncio.to_thread(gate.end)
    await asyncio.wait_for(waiter, 5.0)


async def test_a_request_never_waits_longer_than_the_bound() -> None:
    gate = TriggerFirst(max_wait_s=0.05, hold_loop=False)
    gate.bind(asyncio.get_running_loop())
    gate.begin()  # and never ends: a station triggering back to back
    t = time.monotonic()
    await asyncio.wait_for(gate.wait(), 5.0)
    assert time.monotonic() - t >= 0.04 and gate.busy and gate.waiting == 0
    off = TriggerFirst(max_wait_s=0.0)  # 0 switches the waiting off
    off.bind(asyncio.get_running_loop())
    off.begin()
    await asyncio.wait_for(off.wait(), 1.0)
    assert off.held == 0
    with pytest.raises(ValueError, match="max_wait_s"):
        TriggerFirst(max_wait_s=-1.0)


def test_threadpool_code_waits_for_the_trigger_too() -> None:
    gate = TriggerFirst(max_wait_s=10.0)
    gate.begin()
    order: list[str] = []
    waiting = threading.Thread(target=lambda: (gate.wait_in_thread(), order.append("request")))
    waiting.start()
    waiting.join(0.05)  # still blocked: the trigger runs
    assert waiting.is_alive()
    order.append("trigger ended")
    gate.end()
    waiting.join(5.0)
    assert not waiting.is_alive() and order == ["trigger ended", "request"] and gate.held == 1


def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    """:func:`until` for a thread that is not on the held loop."""
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached before the deadline"
        time.sleep(0.001)


def test_the_http_loop_sleeps_while_a_trigger_runs() -> None:
    """A callback on the HTTP loop waits for the trigger's end; a trigger that never ends holds
    the loop at most the bound."""
    loop = asyncio.new_event_loop()
    runner = threading.Thread(target=loop.run_forever)
    runner.start()
    try:
        gate = TriggerFirst(max_wait_s=10.0)
        asyncio.run_coroutine_threadsafe(_bind(gate), loop).result(5)
        events: list[str] = []
        gate.begin()
        wait_until(lambda: gate.holding == 1)  # the loop has reached the hold
        loop.call_soon_threadsafe(events.append, "callback")
        time.sleep(0.05)  # the loop may run the callback only if the hold let it go
        assert events == [] and gate.holding == 1
        events.append("trigger ended")
        gate.end()
        wait_until(lambda: len(events) == 2)
        assert events == ["trigger ended", "callback"] and gate.holding == 0

        gate.max_wait_s = 0.05  # a trigger that does not end: the loop goes on after the bound
        t = time.monotonic()
        gate.begin()
        done = asyncio.run_coroutine_threadsafe(asyncio.sleep(0), loop)
        done.result(5)
        assert 0.04 <= time.monotonic() - t < 2.0 and gate.busy
        gate.end()
        off = TriggerFirst(max_wait_s=10.0, hold_loop=False)
        asyncio.run_coroutine_threadsafe(_bind(off), loop).result(5)
        off.begin()  # no hold: the loop answers at once
        asyncio.run_coroutine_threadsafe(asyncio.sleep(0), loop).result(1.0)
        assert off.holding == 0
        off.end()
    finally:
        loop.call_soon_threadsafe(loop.stop)
        runner.join(10)
        loop.close()


async def _bind(gate: TriggerFirst) -> None:
    gate.bind(asyncio.get_running_loop())


async def test_http_requests_wait_for_a_running_trigger(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    async with running_station(settings, runtime_options()) as lb:
        gate = lb.runtime.gate
        assert gate.max_wait_s == pytest.approx(0.1) and gate.hold_loop
        async with httpx.AsyncClient(base_url=lb.base_url + "/api/v1", timeout=20,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            # A long trigger, as the gate sees it, started and ended by another thread; the
            # requests are sent from threads of their own once the server's loop (on a thread
            # of its own, as in production) sleeps in the hold.
            gate.max_wait_s = 30.0
            answers: dict[str, int] = {}

            def get(path: str) -> None:
                with httpx.Client(base_url=lb.base_url + "/api/v1", timeout=20,
                                  headers={"Authorization": f"Bearer {ENGINEER}"}) as c:
                    answers[path] = c.get(path).status_code

            def trigger_thread() -> list[str]:
                gate.begin()
                wait_until(lambda: gate.holding == 1)
                clients = [threading.Thread(target=get, args=(p,)) for p in ("/health/ready",
                                                                             "/health/live")]
                for c in clients:
                    c.start()
                for c in clients:
                    c.join(0.05)  # no answer can come while the loop sleeps
                seen = [f"answered {sorted(answers)}", "trigger ended"]
                gate.end()
                for c in clients:
                    c.join(20)
                return seen + [f"{k} {v}" for k, v in sorted(answers.items())]

            assert await asyncio.to_thread(trigger_thread) == [
                "answered []", "trigger ended", "/health/live 200", "/health/ready 200"]
            gate.max_wait_s = 0.1
            # A real PLC trigger marks the gate and leaves it idle when it is done.
            recipe = lb.runtime.active.config
            T = recipe.T_rf_from_pf0.matrix.copy()
            await move_part(lb.runtime, lb.twin, T)
            status, _ = await trigger(lb.twin, recipe, 9, T)
            assert status.result_code == 0
            await until(lambda: not gate.busy)
            rest = (await api.get("/station/status")).json()["rest"]
            assert rest == {"yield_ms": pytest.approx(100.0), "answer_read_wait_ms": 20.0,
                            "held_for_triggers": gate.held}


def test_one_request_waits_at_its_checkpoints_at_most_the_bound_in_total() -> None:
    gate = TriggerFirst(max_wait_s=0.05)
    gate.begin()  # a trigger that does not end while the request runs
    try:
        pause = gate.budget()
        t = time.monotonic()
        for _ in range(20):  # a long page: 20 checkpoints
            pause()
        took = time.monotonic() - t
        # the first checkpoint waits out the bound, the others find it spent
        assert 0.045 <= took < 0.5 and gate.held == 1
    finally:
        gate.end()
    idle = TriggerFirst(max_wait_s=0.05).budget()
    idle()  # no trigger: returns at once and is not counted


def test_a_page_being_built_stops_at_its_checkpoints_while_a_trigger_runs(tmp_path: Path) -> None:
    """A MES list request already past the middleware when a trigger starts: the store calls
    the checkpoint after its query and every 10 rows, and the rows after it wait."""
    from records import make_record

    from server.store import open_store
    from server.store.schemas import MeasurementFilter

    store = open_store(f"sqlite:///{tmp_path / 'store.db'}", "station1")
    try:
        rng = np.random.default_rng(3)
        for i in range(1, 26):
            store.measurements.insert(make_record(rng, trigger_id=i))
        gate = TriggerFirst(max_wait_s=10.0)
        calls: list[bool] = []  # at each checkpoint: was a trigger running when it returned?

        def checkpoint() -> None:
            if len(calls) == 1:
                gate.begin()  # a trigger starts while the page is being built
            gate.wait_in_thread()
            calls.append(gate.busy)

        result: list[int] = []
        page = threading.Thread(target=lambda: result.extend(
            m.id for m in store.measurements.summary_page(MeasurementFilter(), None, 25,
                                                         pause=checkpoint)[0]))
        page.start()
        page.join(0.2)
        assert page.is_alive() and len(calls) == 1 and result == []  # held at the 2nd checkpoint
        gate.end()
        page.join(10.0)
        assert not page.is_alive()
        assert len(calls) == 3 and not any(calls) and len(result) == 25 and gate.held == 1
    finally:
        store.close()


def test_the_collector_waits_while_triggers_run_and_resumes_after_the_last() -> None:
    import gc

    assert gc.isenabled()
    a, b = CollectorPause(), CollectorPause()
    a.begin()
    b.begin()  # a second runtime's trigger in the same process: one collector, counted together
    assert not gc.isenabled() and a.paused and b.paused
    a.end()
    assert not gc.isenabled()  # b's trigger still runs
    b.end()
    assert gc.isenabled() and not a.paused and not b.paused
    a.end()  # an extra end changes nothing
    assert gc.isenabled()
    a.begin()
    a.close()  # a runtime stopped during a trigger gives the collector back
    assert gc.isenabled() and not a.paused
    off = CollectorPause(enabled=False)
    off.begin()
    assert gc.isenabled()
    off.end()


async def test_a_served_station_pauses_the_collector_only_during_triggers(
    tmp_path: Path,
) -> None:
    import gc

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    async with running_station(settings, runtime_options()) as lb:
        assert gc.get_freeze_count() > 0  # start-up's objects are out of the collector's way
        recipe = lb.runtime.active.config
        T = recipe.T_rf_from_pf0.matrix.copy()
        await move_part(lb.runtime, lb.twin, T)
        seen: list[bool] = []
        real = lb.runtime.runner.run

        def observed(*args: object) -> object:  # the real run, noting the collector's state
            seen.append(gc.isenabled())
            return real(*args)

        lb.runtime.runner.run = observed  # type: ignore[method-assign]
        status, _ = await trigger(lb.twin, recipe, 5, T)
        assert status.result_code == 0 and seen == [False]
        await until(lambda: gc.isenabled())
    assert gc.isenabled() and gc.get_freeze_count() == 0


@pytest.mark.parametrize("wait_ms", [60_000.0, 50.0])
async def test_a_plc_trigger_holds_rest_until_the_plc_has_read_its_answer(
    tmp_path: Path, wait_ms: float
) -> None:
    import dataclasses

    from drivers.plc import Status

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    opts = dataclasses.replace(runtime_options(), answer_read_wait_ms=wait_ms)
    async with running_station(settings, opts) as lb:
        rt, twin = lb.runtime, lb.twin
        recipe = rt.active.config
        T = recipe.T_rf_from_pf0.matrix.copy()
        await move_part(rt, twin, T)
        await twin.wait_for(lambda s: s.has(Status.READY), 5.0, "READY")
        await twin.write_trigger(31)
        await until(lambda: rt.plc.machine.result_id == 1)  # published
        if wait_ms > 1000:  # a long bound: only the PLC's read can end the hold
            assert rt.gate.busy and rt.collector.paused
            status = await twin.read_status()
            assert status.has(Status.RESULT_VALID | Status.RESULT_OK) and status.trigger_id == 31
        # else a PLC that does not read: the hold ends wait_ms after the outcome at the latest
        await until(lambda: not rt.gate.busy and not rt.collector.paused)
