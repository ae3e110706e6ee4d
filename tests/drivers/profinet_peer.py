"""profinet-py (GPL-3.0, a test dependency only) as the IO-controller of the tests, in a
network namespace of its own behind a veth pair the tests create; the PLC twin's port over its
cyclic data. Used by tests/drivers/test_profinet.py and the link behaviour suite."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from drivers.links import layout
from drivers.links.layout import ByteOrder, Status
from drivers.links.profinet import modules as mod
from drivers.links.twin import PlcTwin

CONTROLLER = Path(__file__).with_name("profinet_controller.py")
SLOTS = [[s.slot, s.subslot, s.input_length, s.output_length, s.module_ident,
          s.submodule_ident] for s in mod.SUBMODULES]


def usable() -> str | None:
    """Why the PROFINET tests cannot run here, or None."""
    try:
        import profinet  # noqa: F401 - only whether the test extra is installed
    except ImportError:
        return "profinet-py (the independent IO-controller) is not installed (test extras)"
    if os.geteuid() != 0:
        return "the PROFINET tests create a network namespace and a veth pair: they need root"
    return None


@dataclass
class Net:
    """A veth pair: the device's end in this namespace, the controller's in ``ns``."""

    ns: str
    device_if: str
    controller_if: str
    device_ip: str
    controller_ip: str


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True)


@contextlib.contextmanager
def veth(k: int = 0) -> Iterator[Net]:
    tag = f"{os.getpid() % 10000}{k}"
    n = Net(f"pnc{tag}", f"pnd{tag}", f"pnc{tag}", f"10.251.{k}.1", f"10.251.{k}.2")
    ip("netns", "add", n.ns)
    try:
        ip("link", "add", n.device_if, "type", "veth", "peer", "name", n.controller_if)
        ip("link", "set", n.controller_if, "netns", n.ns)
        ip("addr", "add", f"{n.device_ip}/24", "dev", n.device_if)
        ip("link", "set", n.device_if, "up")
        ip("-n", n.ns, "addr", "add", f"{n.controller_ip}/24", "dev", n.controller_if)
        ip("-n", n.ns, "link", "set", n.controller_if, "up")
        ip("-n", n.ns, "link", "set", "lo", "up")
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

    async def run_ar(self, name: str, **connect: Any) -> dict[str, Any]:
        """Connect with the device's own submodules, PrmEnd, ApplicationReady, cyclic data.
        The data hold time defaults to 100 cycles: profinet-py's sender is Python threads on
        a shared 2-core machine and misses whole runs of cycles (a hardware PLC does not)."""
        connect.setdefault("data_hold_factor", 100)
        answer = await self.ok("connect", name=name, slots=SLOTS, **connect)
        await self.ok("prm_end")
        await self.ok("app_ready")
        await self.ok("cyclic")
        return answer


@contextlib.asynccontextmanager
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
async def plc(ctl: Controller, ready: bool = False) -> AsyncIterator[PlcTwin]:
    """The twin as a PLC program runs it: its heartbeat in a cyclic task of its own; with
    ``ready``, trigger enabled, an old watchdog error reset and the station READY."""
    twin = PlcTwin(ControllerPort(ctl), poll_s=0.002)
    await twin.connect()
    beat = asyncio.create_task(twin.keep_alive(0.1))
    try:
        if ready:
            await twin.wait_for(lambda s: s.has(Status.ONLINE), 10.0, "ONLINE")
            status = await twin.enable()
            if status.has(Status.ERROR):
                await twin.reset_error(timeout=5.0)
            await twin.wait_for(lambda s: s.has(Status.READY), 10.0, "READY")
        yield twin
    finally:
        twin.stop_keep_alive()
        await beat
