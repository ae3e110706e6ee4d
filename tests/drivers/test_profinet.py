"""The PROFINET IO-device against an IO-controller we did not write (profinet-py, GPL-3.0,
a test dependency only), over a veth pair whose controller end is in a network namespace the
test creates. The device runs as the station runs it: ProfinetLink, its child process, the
shared handshake; the PLC program is the layout's twin over the controller's cyclic data."""

from __future__ import annotations

import asyncio
import os
import signal
from collections.abc import AsyncIterator, Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pytest

from drivers.links import layout
from drivers.links.base import AlarmNotice
from drivers.links.layout import Status
from drivers.links.profinet import ProfinetLink, im
from drivers.links.profinet import modules as mod
from drivers.links.profinet.settings import ProfinetLinkConfig
from tests.drivers import profinet_peer as peer
from tests.drivers.plc_peers import ArithmeticHandler, published_offset
from tests.waiting import until

if (why := peer.usable()) is not None:
    pytest.skip(why, allow_module_level=True)

NAME = "mvpose-cell-7"
SLOTS = peer.SLOTS
Controller = peer.Controller


@pytest.fixture(scope="module")
def net() -> Iterator[peer.Net]:
    with peer.veth(0) as n:
        yield n


@pytest.fixture
async def controller(net: peer.Net) -> AsyncIterator[peer.Controller]:
    async with peer.controller(net) as ctl:
        yield ctl


@pytest.fixture
async def device(net: peer.Net, tmp_path: Path
                 ) -> AsyncIterator[tuple[ProfinetLink, ArithmeticHandler]]:
    handler = ArithmeticHandler()
    handler.recipe = 1  # the link selects the station's recipe at its start
    cfg = ProfinetLinkConfig(interface=net.device_if, station_name=NAME, rpc_host=net.device_ip,
                             watchdog_s=1.0, state_dir=str(tmp_path))
    link = ProfinetLink(cfg, handler)
    await link.start()
    try:
        yield link, handler
    finally:
        await link.stop()


def _plc(ctl: peer.Controller) -> Any:
    return peer.plc(ctl)


async def _run_ar(ctl: peer.Controller, **connect: Any) -> dict[str, Any]:
    return await ctl.run_ar(NAME, **connect)


async def test_dcp_finds_the_device_and_names_it(device: Any, controller: Controller,
                                                 net: peer.Net) -> None:
    link, _ = device
    found = (await controller.ok("identify"))["devices"]
    assert [(d["name"], d["ip"], d["vendor_id"], d["device_id"]) for d in found] == [
        (NAME, net.device_ip, "0xffff" if isinstance(found[0]["vendor_id"], str) else 0xFFFF,
         found[0]["device_id"])]
    assert (await controller.ok("identify", name=NAME))["devices"][0]["name"] == NAME
    mac = found[0]["mac"]
    assert (await controller.ok("set_name", mac=mac, name="cell-8-vision"))["set"] is True
    await until(lambda: link.child_stats.get("station_name") == "cell-8-vision",
                "the new NameOfStation in the device's status")
    assert (await controller.ok("identify", name="cell-8-vision"))["devices"]
    assert (await controller.ok("set_name", mac=mac, name=NAME))["set"] is True


async def test_connect_cyclic_trigger_result_and_release(
        device: Any, controller: Controller) -> None:
    link, handler = device
    await _run_ar(controller)
    await until(lambda: (link.child_stats.get("ar") or {}).get("phase") == "data",
                "the AR in data exchange")
    async with _plc(controller) as twin:
        ready = await twin.enable()
        assert ready.test_float == pytest.approx(layout.TEST_FLOAT, abs=1e-4)
        assert ready.test_int == layout.TEST_INT
        for trigger_id in (91001, 91013):  # 91013 = 13 × 7001: a NOK of the arithmetic handler
            answer = await twin.cycle(trigger_id, part_id="WVWZZZ1KZ", timeout=5.0)
            assert answer.trigger_id == trigger_id
            assert answer.result_id == handler.seq
            assert answer.offset_float == pytest.approx(published_offset(trigger_id), abs=1e-4)
            assert answer.has(Status.RESULT_OK) == (trigger_id % 13 != 0)
    assert [r.part_id for r in handler.requests] == ["WVWZZZ1KZ"] * 2
    assert {r.link for r in handler.requests} == {"profinet"}
    await until(lambda: link.status().get("cycle_jitter_ms") is not None,
                "the cycle's jitter measured")
    im0 = bytes.fromhex((await controller.ok("read", slot=0, subslot=1, index=0xAFF0))["hex"])
    assert b"MVPOSE-PN" in im0
    await controller.ok("stop_cyclic")
    await controller.ok("release")
    await until(lambda: link.child_stats.get("releases") == 1 and
                link.child_stats.get("ar") is None, "the AR released")


async def test_a_stopped_controller_is_a_lost_plc_and_it_reconnects(
        device: Any, controller: Controller) -> None:
    link, handler = device
    await _run_ar(controller)
    async with _plc(controller) as twin:
        await twin.enable()
        await twin.wait_for(lambda s: s.has(Status.READY), 5.0, "READY")
    await controller.ok("stop_cyclic")  # the controller goes silent: no Release
    await until(lambda: link.child_stats.get("data_hold_expired") == 1,
                "the data hold time expired")
    await until(lambda: link.status()["watchdog_trips"] >= 1,
                f"the handshake's watchdog reporting the lost PLC ({link.status()})")
    assert any("data hold time" in e for e in link.status()["last_errors"])
    # the controller comes back: a new AR
    await _run_ar(controller)
    async with _plc(controller) as twin:
        await twin.wait_for(lambda s: s.has(Status.ONLINE), 5.0, "ONLINE")
        await twin.reset_error(timeout=5.0)
        await twin.enable()
        answer = await twin.cycle(92001, timeout=5.0)
        assert answer.trigger_id == 92001 and answer.result_id == handler.seq
    await until(lambda: link.child_stats.get("connects") == 2, "the second AR counted")


async def test_a_camera_down_is_a_diagnosis_alarm_that_disappears(
        device: Any, controller: Controller) -> None:
    link, _ = device
    await _run_ar(controller)
    await controller.ok("listen_alarms")
    await until(lambda: (link.child_stats.get("ar") or {}).get("phase") == "data",
                "the AR in data exchange")
    link.alarm_changed(_Notice("raised", "camera:left1", "CAMERA_DOWN"))
    link.alarm_changed(_Notice("raised", "link:modbus", "LINK_NO_PLC"))  # not a diagnosis

    async def alarms() -> list[list[int]]:
        got: list[list[int]] = (await controller.ok("alarms"))["alarms"]
        return got

    want = [[0x0001, mod.RESULT.slot, mod.RESULT.subslot]]
    for _ in range(500):
        if await alarms() == want:
            break
        await asyncio.sleep(0.01)
    assert await alarms() == want
    link.alarm_changed(_Notice("cleared", "camera:left1", "CAMERA_DOWN"))
    want.append([0x000C, mod.RESULT.slot, mod.RESULT.subslot])  # diagnosis disappears
    for _ in range(500):
        if await alarms() == want:
            break
        await asyncio.sleep(0.01)
    assert await alarms() == want
    await until(lambda: (link.child_stats.get("ar") or {}).get("alarms_acked") == 2,
                "both alarms acknowledged by the controller")


def _Notice(event: str, source: str, code: str) -> AlarmNotice:  # noqa: N802 - reads as one
    return AlarmNotice(event, 1, 1, source, code, "high", code, event == "raised", False, None,
                       datetime.now(UTC))


async def test_wrong_submodules_get_a_module_diff(device: Any, controller: Controller) -> None:
    link, _ = device
    wrong = [list(s) for s in SLOTS]
    wrong[1][5] = 0x99  # another submodule ident in slot 1
    await controller.ok("connect", name=NAME, slots=wrong)
    await until(lambda: link.child_stats.get("module_diffs") == 1, "the ModuleDiffBlock counted")
    await controller.ok("release")


async def test_malformed_frames_are_counted_never_a_crash(
        device: Any, controller: Controller, net: peer.Net) -> None:
    link, _ = device
    me = (await controller.ok("raw", hex="ff" * 12 + "8892" + "fefe05"))["mac"]
    src = me.replace(":", "")
    bad = [
        "010ecf000000" + src + "8892" + "fefe0500000000010080ffff",  # length past the frame
        "010ecf000000" + src + "8892" + "fefe05000000000100000004ffff0010",  # block too long
    ]
    for frame in bad:
        await controller.ok("raw", hex=frame.ljust(120, "0"))
    await controller.ok("udp", ip=net.device_ip, hex="04" + "00" * 40)  # RPC header cut short
    await until(lambda: link.child_stats.get("malformed", 0) >= 3, "the bad frames counted")
    assert link.ready()
    assert (await controller.ok("identify", name=NAME))["devices"]


async def test_the_interface_going_down_is_not_the_end_of_the_device(
        device: Any, controller: Controller, net: peer.Net) -> None:
    link, _ = device
    await _run_ar(controller)
    peer.ip("link", "set", net.device_if, "down")
    try:
        await until(lambda: link.child_stats.get("send_errors", 0) > 0,
                    "the frames that could not be sent counted")
        assert link.ready()
    finally:
        peer.ip("link", "set", net.device_if, "up")
    await controller.ok("stop_cyclic")
    await until(lambda: link.child_stats.get("ar") is None, "the AR ended (data hold time)")
    found = (await controller.ok("identify", name=NAME))["devices"]
    assert [d["name"] for d in found] == [NAME]


async def test_a_device_process_that_dies_is_started_again(
        device: Any, controller: Controller) -> None:
    link, _ = device
    assert link._proc is not None
    os.kill(link._proc.pid, signal.SIGKILL)
    await until(lambda: link.status().get("restarts") == 1 and link.ready(),
                "the device's process started again")
    assert any("ended" in e for e in link.runner.stats.last_errors)
    found = (await controller.ok("identify", name=NAME))["devices"]
    assert [d["name"] for d in found] == [NAME]


async def _restarted(link: ProfinetLink, n: int) -> None:
    assert link._proc is not None
    os.kill(link._proc.pid, signal.SIGKILL)
    await until(lambda: link.status().get("restarts") == n and link.ready(),
                "the device's process started again")


async def test_dcp_set_ip_moves_the_device_and_a_permanent_one_survives_a_restart(
        device: Any, controller: Controller, net: peer.Net, tmp_path: Path) -> None:
    link, handler = device
    mac = (await controller.ok("identify", name=NAME))["devices"][0]["mac"]
    new = net.device_ip.rsplit(".", 1)[0] + ".5"

    async def set_ip(ip: str, permanent: bool, gateway: str = "0.0.0.0") -> dict[str, Any]:
        return await controller("set_ip", mac=mac, ip=ip, netmask="255.255.255.0",
                                gateway=gateway, permanent=permanent)

    try:
        refused = await set_ip(new, True, gateway="10.9.9.9")  # outside the subnet
        assert not refused["ok"] and "Suboption not set" in refused["error"], refused
        assert (await set_ip(new, True))["set"] is True
        assert (await controller.ok("identify", name=NAME))["devices"][0]["ip"] == new
        # the controller connects at the new address and runs cyclic data
        await _run_ar(controller)
        i_m1 = im.block(im.RECORDS[0xAFF1], im.text(im.RECORDS[0xAFF1], {
            "IM_Tag_Function": "vision body shop", "IM_Tag_Location": "cell 7"}))
        async with _plc(controller) as twin:
            await twin.enable()
            answer = await twin.cycle(93001, timeout=5.0)
            assert answer.trigger_id == 93001 and answer.result_id == handler.seq
        await controller.ok("write", slot=0, subslot=1, index=0xAFF1, hex=i_m1.hex())
        bad = await controller("write", slot=0, subslot=1, index=0xAFF2, hex="00" * 24)
        assert not bad["ok"] and "0xb1" in bad["error"].lower(), bad  # write length error
        await controller.ok("stop_cyclic")
        await controller.ok("release")
        # a restart keeps the permanent address and the I&M record
        await _restarted(link, 1)
        assert (await controller.ok("identify", name=NAME))["devices"][0]["ip"] == new
        await _run_ar(controller)
        got = await controller.ok("read", slot=0, subslot=1, index=0xAFF1)
        assert bytes.fromhex(got["hex"]) == i_m1
        await controller.ok("stop_cyclic")
        await controller.ok("release")
        # a temporary address is dropped on restart: the interface's own comes back
        await until(lambda: link.child_stats.get("ar") is None, "the AR released")
        assert (await set_ip(new.rsplit(".", 1)[0] + ".6", False))["set"] is True
        await _restarted(link, 2)
        assert (await controller.ok("identify", name=NAME))["devices"][0]["ip"] == \
            net.device_ip
    finally:
        peer.ip("addr", "flush", "dev", net.device_if)
        peer.ip("addr", "add", f"{net.device_ip}/24", "dev", net.device_if)


async def test_a_set_ip_is_refused_when_the_station_says_so(
        controller: Controller, net: peer.Net, tmp_path: Path) -> None:
    cfg = ProfinetLinkConfig(interface=net.device_if, station_name=NAME, rpc_host=net.device_ip,
                             state_dir=str(tmp_path), accept_ip_from_controller=False)
    link = ProfinetLink(cfg, ArithmeticHandler())
    await link.start()
    try:
        mac = (await controller.ok("identify", name=NAME))["devices"][0]["mac"]
        for _ in range(2):
            refused = await controller("set_ip", mac=mac, ip=net.device_ip.rsplit(".", 1)[0] + ".7",
                                       netmask="255.255.255.0", gateway="0.0.0.0",
                                       permanent=True)
            assert not refused["ok"] and "SET not possible" in refused["error"], refused
        await until(lambda: [e["kind"] for e in link.events] == ["ip_refused"],
                    "the refusal said once")
        assert (await controller.ok("identify", name=NAME))["devices"][0]["ip"] == \
            net.device_ip
    finally:
        await link.stop()
