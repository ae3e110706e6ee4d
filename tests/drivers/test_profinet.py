"""The PROFINET IO-device against an IO-controller we did not write (profinet-py, GPL-3.0,
a test dependency only), over a veth pair whose controller end is in a network namespace the
test creates. The device runs as the station runs it: ProfinetLink, its child process, the
shared handshake; the PLC program is the layout's twin over the controller's cyclic data."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from drivers.links import layout
from drivers.links.layout import ByteOrder, Status
from drivers.links.profinet import ProfinetLink
from drivers.links.profinet import modules as mod
from drivers.links.profinet.settings import ProfinetLinkConfig
from drivers.links.twin import PlcTwin
from tests.drivers.plc_peers import ArithmeticHandler, published_offset
from tests.waiting import until

pytest.importorskip("profinet", reason="profinet-py (the independent IO-controller) is in the "
                    "test extras")
if os.geteuid() != 0 or shutil.which("ip") is None:
    pytest.skip("the PROFINET tests create a network namespace and a veth pair: they need "
                "root and iproute2", allow_module_level=True)

CONTROLLER = Path(__file__).with_name("profinet_controller.py")
DEVICE_IP, CONTROLLER_IP = "10.251.0.1", "10.251.0.2"
NAME = "mvpose-cell-7"
SLOTS = [[s.slot, s.subslot, s.input_length, s.output_length, s.module_ident,
          s.submodule_ident] for s in mod.SUBMODULES]


@dataclass
class Net:
    ns: str
    device_if: str
    controller_if: str


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@pytest.fixture(scope="module")
def net() -> Iterator[Net]:
    tag = f"{os.getpid() % 100000}"
    n = Net(f"pnc{tag}", f"pnd{tag}", f"pnc{tag}")
    _ip("netns", "add", n.ns)
    try:
        _ip("link", "add", n.device_if, "type", "veth", "peer", "name", n.controller_if)
        _ip("link", "set", n.controller_if, "netns", n.ns)
        _ip("addr", "add", f"{DEVICE_IP}/24", "dev", n.device_if)
        _ip("link", "set", n.device_if, "up")
        _ip("-n", n.ns, "addr", "add", f"{CONTROLLER_IP}/24", "dev", n.controller_if)
        _ip("-n", n.ns, "link", "set", n.controller_if, "up")
        _ip("-n", n.ns, "link", "set", "lo", "up")
        yield n
    finally:
        subprocess.run(["ip", "link", "del", n.device_if], capture_output=True)
        subprocess.run(["ip", "netns", "del", n.ns], capture_output=True)


class Controller:
    """profinet-py in the controller's namespace, one JSON command at a time."""

    def __init__(self, proc: asyncio.subprocess.Process) -> None:
        self.proc = proc
        self.lock = asyncio.Lock()  # the twin's heartbeat task shares the channel

    async def __call__(self, do: str, **args: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        async with self.lock:
            self.proc.stdin.write(json.dumps({"do": do, **args}).encode() + b"\n")
            await self.proc.stdin.drain()
            line = await asyncio.wait_for(self.proc.stdout.readline(), 30)
        answer: dict[str, Any] = json.loads(line)
        return answer

    async def ok(self, do: str, **args: Any) -> dict[str, Any]:
        answer = await self(do, **args)
        assert answer["ok"], answer
        return answer


@pytest.fixture
async def controller(net: Net) -> AsyncIterator[Controller]:
    proc = await asyncio.create_subprocess_exec(
        "ip", "netns", "exec", net.ns, sys.executable, str(CONTROLLER), net.controller_if,
        stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        yield Controller(proc)
    finally:
        if proc.returncode is None:
            proc.kill()
        await proc.wait()


@pytest.fixture
async def device(net: Net) -> AsyncIterator[tuple[ProfinetLink, ArithmeticHandler]]:
    handler = ArithmeticHandler()
    handler.recipe = 1  # the link selects the station's recipe at its start
    cfg = ProfinetLinkConfig(interface=net.device_if, station_name=NAME, rpc_host=DEVICE_IP,
                             watchdog_s=1.0)
    link = ProfinetLink(cfg, handler)
    await link.start()
    try:
        yield link, handler
    finally:
        await link.stop()


class ControllerPort:
    """The twin's PlcPort over the controller's cyclic data: slot 1 and 2 carry the PLC's
    outputs, slot 3 its inputs (big-endian, as PROFINET carries them)."""

    byte_order = ByteOrder.BIG
    word_order = ByteOrder.BIG.word_order

    def __init__(self, ctl: Controller) -> None:
        self.ctl = ctl
        self.outputs = bytearray(layout.OUTPUT_SIZE)

    async def connect(self) -> None:
        pass

    async def read_inputs(self) -> bytes:
        answer = await self.ctl.ok("input", slot=mod.RESULT.slot, subslot=1)
        return bytes.fromhex(answer["hex"]) if answer["hex"] else bytes(layout.INPUT_SIZE)

    async def write_outputs(self, offset: int, data: bytes) -> None:
        self.outputs[offset:offset + len(data)] = data
        # the pose and part id before the control word: a frame sent between the two writes
        # must not carry a TRIGGER edge without its data (a PLC writes its outputs as one)
        await self.ctl.ok("output", slots=[
            [sub.slot, sub.subslot, bytes(self.outputs[sub.output[0]:sum(sub.output)]).hex()]
            for sub in (mod.ROBOT_POSE, mod.HANDSHAKE)])

    def close(self) -> None:
        pass

    def abort(self) -> None:
        pass


@contextlib.asynccontextmanager
async def _plc(ctl: Controller) -> AsyncIterator[PlcTwin]:
    """The twin as a PLC program runs it: its heartbeat in a cyclic task of its own."""
    twin = PlcTwin(ControllerPort(ctl))
    await twin.connect()
    beat = asyncio.create_task(twin.keep_alive(0.1))
    try:
        yield twin
    finally:
        twin.stop_keep_alive()
        await beat


async def _run_ar(ctl: Controller, **connect: Any) -> dict[str, Any]:
    answer = await ctl.ok("connect", name=NAME, slots=SLOTS, **connect)
    await ctl.ok("prm_end")
    await ctl.ok("app_ready")
    await ctl.ok("cyclic")
    return answer


async def test_dcp_finds_the_device_and_names_it(device: Any, controller: Controller) -> None:
    link, _ = device
    found = (await controller.ok("identify"))["devices"]
    assert [(d["name"], d["ip"], d["vendor_id"], d["device_id"]) for d in found] == [
        (NAME, DEVICE_IP, "0xffff" if isinstance(found[0]["vendor_id"], str) else 0xFFFF,
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


@dataclass(frozen=True)
class _Notice:
    """The fields of the station's AlarmNotice the link reads (docs/alarms.md)."""

    event: str
    source: str
    code: str


async def test_wrong_submodules_get_a_module_diff(device: Any, controller: Controller) -> None:
    link, _ = device
    wrong = [list(s) for s in SLOTS]
    wrong[1][5] = 0x99  # another submodule ident in slot 1
    await controller.ok("connect", name=NAME, slots=wrong)
    await until(lambda: link.child_stats.get("module_diffs") == 1, "the ModuleDiffBlock counted")
    await controller.ok("release")


async def test_malformed_frames_are_counted_never_a_crash(
        device: Any, controller: Controller) -> None:
    link, _ = device
    me = (await controller.ok("raw", hex="ff" * 12 + "8892" + "fefe05"))["mac"]
    src = me.replace(":", "")
    bad = [
        "010ecf000000" + src + "8892" + "fefe0500000000010080ffff",  # length past the frame
        "010ecf000000" + src + "8892" + "fefe05000000000100000004ffff0010",  # block too long
    ]
    for frame in bad:
        await controller.ok("raw", hex=frame.ljust(120, "0"))
    await controller.ok("udp", ip=DEVICE_IP, hex="04" + "00" * 40)  # RPC header cut short
    await until(lambda: link.child_stats.get("malformed", 0) >= 3, "the bad frames counted")
    assert link.ready()
    assert (await controller.ok("identify", name=NAME))["devices"]
