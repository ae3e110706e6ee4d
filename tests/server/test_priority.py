"""Triggers first: HTTP requests wait for a running trigger, bounded, and liveness never waits."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable
from pathlib import Path

import httpx
import pytest
from stations import ENGINEER, relaxed_deadline, runtime_options, settings_for, station_file

from server.loopback import move_part, running_station, trigger
from server.priority import TriggerFirst

pytestmark = pytest.mark.timeout(120)


async def until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "condition not reached before the deadline"
        await asyncio.sleep(0.002)


async def test_a_waiting_request_goes_on_only_after_the_trigger_ends() -> None:
    gate = TriggerFirst(max_wait_s=10.0)
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
    gate = TriggerFirst(max_wait_s=10.0)
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
    gate = TriggerFirst(max_wait_s=0.05)
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


async def test_http_requests_wait_for_a_running_trigger_but_liveness_does_not(
    tmp_path: Path,
) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    async with running_station(settings, runtime_options()) as lb:
        gate = lb.runtime.gate
        assert gate.max_wait_s == pytest.approx(0.1)
        async with httpx.AsyncClient(base_url=lb.base_url + "/api/v1", timeout=20,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            # A long trigger, as the gate sees it (held open here so the test decides when it
            # ends; the bound is raised so the request cannot time out of the wait meanwhile).
            gate.max_wait_s = 30.0
            await asyncio.to_thread(gate.begin)
            ready = asyncio.create_task(api.get("/health/ready"))
            await until(lambda: gate.waiting == 1)
            live = await api.get("/health/live")
            assert live.status_code == 200 and not ready.done()
            await asyncio.to_thread(gate.end)
            assert (await asyncio.wait_for(ready, 10.0)).status_code == 200
            gate.max_wait_s = 0.1
            # A real PLC trigger marks the gate and leaves it idle when it is done.
            recipe = lb.runtime.active.config
            T = recipe.T_rf_from_pf0.matrix.copy()
            await move_part(lb.runtime, lb.twin, T)
            status, _ = await trigger(lb.twin, recipe, 9, T)
            assert status.result_code == 0 and not gate.busy
            rest = (await api.get("/station/status")).json()["rest"]
            assert rest == {"yield_ms": pytest.approx(100.0), "held_for_triggers": gate.held}
            assert gate.held >= 1
