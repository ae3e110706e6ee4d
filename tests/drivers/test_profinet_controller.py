"""Our IO-controller's sans-I/O core against the device's, frame by frame on a clock we move:
Identify by name, Connect, PrmEnd, ApplicationReady, cyclic data both ways, a diagnosis alarm
acknowledged, Release, a ModuleDiff, a silent device (data hold), DCP Set (name, IP) and the
I&M records read and written."""

from __future__ import annotations

import struct
from collections.abc import Callable

import pytest

from drivers.links import layout
from drivers.links.profinet import cyclic, im
from drivers.links.profinet import frames as fr
from drivers.links.profinet import modules as mod
from drivers.links.profinet.controller import Controller
from drivers.links.profinet.device import Device, Identity, Out

DEV_MAC = bytes.fromhex("020000000001")
PLC_MAC = bytes.fromhex("020000000002")
DEV_IP = ("10.0.0.1", 34964)
PLC_IP = ("10.0.0.2", 34964)


def make_device(name: str = "mvpose-cell-7") -> Device:
    return Device(Identity(DEV_MAC, name, (bytes([10, 0, 0, 1]), bytes([255, 255, 255, 0]),
                                           bytes(4))))


class Wire:
    """Both cores on one Ethernet segment and one IP network; the events each one saw."""

    def __init__(self, dev: Device, ctl: Controller) -> None:
        self.dev, self.ctl = dev, ctl
        self.now = 0.0
        self.dev_events: list[str] = []
        self.ctl_events: list[str] = []
        self.texts: list[str] = []  # the controller's events, said
        self.outputs: list[bytes] = []  # the device's output images, as they changed
        self.sends: dict[bool, list[float]] = {True: [], False: []}  # cyclic frames, by sender

    def deliver(self, out: Out, from_ctl: bool) -> None:
        todo = [(out, from_ctl)]
        while todo:
            o, ctl_sent = todo.pop(0)
            if o.cyclic:
                self.sends[ctl_sent].append(self.now)
            (self.ctl_events if ctl_sent else self.dev_events).extend(e.kind for e in o.events)
            if ctl_sent:
                self.texts.extend(e.text for e in o.events)
            if not ctl_sent and o.output is not None:
                self.outputs.append(o.output)
            for frame in o.frames:
                todo.append((self.dev.on_frame(frame, self.now), False) if ctl_sent else
                            (self.ctl.on_frame(frame, self.now), True))
            dev_ip = (".".join(map(str, self.dev.identity.ip[0])), DEV_IP[1])
            for data, addr in o.datagrams:
                if ctl_sent:
                    assert addr == dev_ip
                    todo.append((self.dev.on_datagram(data, PLC_IP, self.now), False))
                else:
                    assert addr == PLC_IP
                    todo.append((self.ctl.on_datagram(data, dev_ip, self.now), True))

    def run(self, until: Callable[[], bool], step: float = 0.001, limit: float = 5.0) -> None:
        end = self.now + limit
        while not until():
            assert self.now < end, (self.ctl.phase, self.ctl_events, self.dev_events)
            self.now += step
            self.deliver(self.ctl.tick(self.now), True)
            self.deliver(self.dev.tick(self.now), False)


def connected(dev: Device, **kw: object) -> Wire:
    ctl = Controller(PLC_MAC, dev.identity.station_name, **kw)  # type: ignore[arg-type]
    wire = Wire(dev, ctl)
    wire.deliver(ctl.start(0.0), True)
    wire.run(lambda: ctl.phase == "data" and dev.ar is not None and dev.ar.phase == "data")
    return wire


def test_identify_connect_prm_end_application_ready_and_cyclic_data_both_ways() -> None:
    dev = make_device()
    wire = connected(dev)
    ctl = wire.ctl
    assert wire.ctl_events == ["found", "connected", "running"]
    assert wire.dev_events == ["connected", "running"]
    assert ctl.diff == () and ctl.device is not None and ctl.device.mac == DEV_MAC
    assert dev.ar is not None and dev.ar.input_cr.cycle_us == 4000
    # the PLC's outputs reach the device's output image, the station's inputs the controller
    ctl.output_image = bytes(i & 0xFF for i in range(layout.OUTPUT_SIZE))
    wire.run(lambda: dev.output_image == ctl.output_image)
    dev.input_image = bytes((7 * i) & 0xFF for i in range(layout.INPUT_SIZE))
    wire.run(lambda: ctl.input_image == dev.input_image)
    # both send a frame per 4 ms cycle
    sent = ctl.stats.frames_out, dev.stats.frames_out
    wire.run(lambda: wire.now >= 1.0)
    assert 240 <= ctl.stats.frames_out - sent[0] <= 260
    assert 240 <= dev.stats.frames_out - sent[1] <= 260
    # a diagnosis alarm is acknowledged (the device's one in flight is done)
    wire.deliver(dev.diagnosis("camera:cam1", True, 0x0100, wire.now), False)
    assert wire.ctl_events[-1] == "alarm" and ctl.stats.alarms == 1
    assert dev.ar.alarm.acked == 1 and dev.ar.alarm.pending is None
    # Release ends the AR on both sides
    wire.deliver(ctl.release(wire.now), True)
    assert "released" in wire.dev_events and wire.ctl_events[-1] == "released"
    assert dev.ar is None and ctl.tick(wire.now + 1).frames == []


def test_the_device_sends_its_input_frame_half_a_cycle_after_the_controllers_output_frame(
) -> None:
    dev = make_device()
    ctl = Controller(PLC_MAC, dev.identity.station_name)
    wire = Wire(dev, ctl)
    wire.now = 0.0003  # the controller's cycle starts off the device's clock
    wire.deliver(ctl.start(wire.now), True)
    wire.run(lambda: wire.now >= 0.5, step=0.00025)
    assert dev.ar is not None and dev.ar.realigned == 1
    ctl_t, dev_t = wire.sends[True][-50:], wire.sends[False][-50:]
    lags = [(d - max(c for c in ctl_t if c <= d)) * 1000 for d in dev_t]
    assert all(1.99 < lag < 2.26 for lag in lags), lags  # 2 ms, on a clock of 0.25 ms steps
    # an answer ready within those 2 ms leaves with the next input frame
    before = len(wire.sends[False])
    ctl.output_image = bytes([1]) + bytes(layout.OUTPUT_SIZE - 1)
    wire.run(lambda: dev.output_image == ctl.output_image, step=0.00025)
    dev.input_image = bytes([2]) + bytes(layout.INPUT_SIZE - 1)  # the station's answer
    wire.run(lambda: ctl.input_image == dev.input_image, step=0.00025)
    assert len(wire.sends[False]) == before + 1
    # one late output frame does not move the phase; eight in a row do
    cyclic.keep_phase(dev.ar, wire.now + 0.002, dev.input_phase_s)
    assert dev.ar.realigned == 1


def test_a_cycle_of_8_ms_and_the_data_hold_factor_reach_the_device() -> None:
    dev = make_device()
    connected(dev, cycle_ms=8.0, data_hold_factor=10)
    assert dev.ar is not None
    assert dev.ar.input_cr.cycle_us == 8000 and dev.ar.hold_s == pytest.approx(0.080)


def test_wrong_expected_submodules_are_reported_as_a_module_diff() -> None:
    dev = make_device()
    wrong = (mod.DAP, mod.HANDSHAKE, mod.ROBOT_POSE,
             mod.Submodule("result", 3, 1, 0x30, 0x99, input=mod.RESULT.input))
    wire = connected(dev, submodules=wrong)
    assert wire.ctl.diff == ((0, 3, 2, 1, 0x9000),)  # proper module, wrong submodule
    assert dev.stats.module_diffs == 1 and "1 submodules differ" in wire.texts[1]


def test_a_silent_device_is_lost_after_the_data_hold_time() -> None:
    dev = make_device()
    wire = connected(dev, data_hold_factor=5)
    ctl = wire.ctl
    wire.dev = make_device("another-device")  # the device stops sending (and answering)
    out = Out()
    now = wire.now
    while not out.events:
        now += 0.001
        out = ctl.tick(now)
    assert [e.kind for e in out.events] == ["lost"] and ctl.phase == "failed"
    assert "20 ms (data hold time)" in out.events[0].text


def test_an_absent_device_fails_after_its_tries_and_a_name_set_by_dcp() -> None:
    dev = make_device()
    ctl = Controller(PLC_MAC, "nobody-here")
    wire = Wire(dev, ctl)
    wire.deliver(ctl.start(0.0), True)
    wire.run(lambda: ctl.phase == "failed", step=0.05, limit=10)
    assert wire.ctl_events == ["failed"]
    assert wire.texts == ["'nobody-here' did not answer DCP Identify (5 tries)"]
    # DCP Set NameOfStation, then the controller finds it by the new name
    wire.deliver(ctl.set_name(DEV_MAC, "nobody-here", wire.now), True)
    assert wire.ctl_events[-1] == "set" and dev.identity.station_name == "nobody-here"
    ctl2 = Controller(PLC_MAC, "nobody-here")
    wire2 = Wire(dev, ctl2)
    wire2.deliver(ctl2.start(0.0), True)
    wire2.run(lambda: ctl2.phase == "data")


def test_cycles_that_are_not_whole_send_clocks_are_refused() -> None:
    with pytest.raises(ValueError, match="2.5 ms is not a whole number"):
        Controller(PLC_MAC, "x", cycle_ms=2.5)
    with pytest.raises(ValueError, match="data hold factor 0"):
        Controller(PLC_MAC, "x", data_hold_factor=0)


def test_random_bytes_are_counted_never_raised() -> None:
    import random

    dev = make_device()
    wire = connected(dev)
    rng = random.Random(4)
    for _ in range(300):
        junk = bytes(rng.randrange(256) for _ in range(rng.randrange(14, 120)))
        raw = PLC_MAC + DEV_MAC + b"\x88\x92" + junk
        wire.ctl.on_frame(raw, wire.now)
        wire.ctl.on_datagram(junk, DEV_IP, wire.now)
    assert wire.ctl.stats.malformed > 0 and wire.ctl.phase == "data"
    assert fr.FRAME_ID_RTC1_MIN <= wire.ctl.output_frame_id <= fr.FRAME_ID_RTC1_MAX


def test_the_product_never_imports_profinet_py() -> None:
    """profinet-py is GPL and a test dependency only: no product module imports it."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    found = []
    for package in ("mvpose_core", "drivers", "server", "bench"):
        for path in (root / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                names = ([a.name for a in node.names] if isinstance(node, ast.Import) else
                         [node.module or ""] if isinstance(node, ast.ImportFrom)
                         and node.level == 0 else [])
                found += [f"{path.relative_to(root)}: {n}" for n in names
                          if n == "profinet" or n.startswith("profinet.")]
    assert found == ["bench/bench_profinet.py: profinet"]  # only to see whether it is there


def test_set_ip_by_dcp_then_the_controller_connects_at_the_new_address() -> None:
    dev = make_device()
    ctl = Controller(PLC_MAC, dev.identity.station_name)
    wire = Wire(dev, ctl)
    new = (bytes([10, 0, 0, 7]), bytes([255, 255, 255, 0]), bytes(4))
    wire.deliver(ctl.set_ip(DEV_MAC, new, 0.0), True)
    assert wire.texts[-1].endswith("done") and dev.identity.ip == new
    wire.deliver(ctl.start(0.0), True)
    wire.run(lambda: ctl.phase == "data")
    assert ctl.device_addr == ("10.0.0.7", 34964) and "10.0.0.7" in wire.texts[-3]
    # while the AR is open another address is refused (its RPC endpoint is the address)
    wire.deliver(ctl.set_ip(DEV_MAC, (bytes([10, 0, 0, 8]), *new[1:]), wire.now), True)
    assert wire.texts[-1].endswith(f"(BlockError {fr.BLOCK_IN_OPERATION})")
    # a gateway outside the subnet is refused
    wire.deliver(ctl.release(wire.now), True)
    wire.deliver(ctl.set_ip(DEV_MAC, (new[0], new[1], bytes([10, 0, 1, 1])), wire.now), True)
    assert wire.texts[-1].endswith(f"(BlockError {fr.BLOCK_SUBOPTION_NOT_SET})")
    assert dev.identity.ip == new


def test_im_records_are_read_and_written_and_bad_lengths_refused() -> None:
    dev = make_device()
    wire = connected(dev)
    ctl = wire.ctl

    def call(out: Out) -> tuple[int, bytes]:
        wire.deliver(out, True)
        assert ctl.record is not None
        return ctl.record

    status, im0 = call(ctl.read_record(0, 1, 0xAFF0, wire.now))
    assert status == 0 and struct.unpack_from(">H", im0, len(im0) - 2)[0] == 0x001E
    rec1 = im.RECORDS[0xAFF1]
    status, data = call(ctl.read_record(0, 1, 0xAFF1, wire.now))
    assert status == 0 and data == im.block(rec1, b" " * 54)  # nobody wrote it yet
    written = im.block(rec1, im.text(rec1, {"IM_Tag_Function": "body-in-white vision",
                                            "IM_Tag_Location": "hall 4 cell 7"}))
    assert call(ctl.write_record(0, 1, 0xAFF1, written, wire.now))[0] == 0
    assert call(ctl.read_record(0, 1, 0xAFF1, wire.now)) == (0, written)
    assert len(written) == 60 and dev.im[0xAFF1][32:].rstrip() == b"hall 4 cell 7"
    rec4 = im.RECORDS[0xAFF4]
    signature = im.block(rec4, bytes(range(54)))
    assert call(ctl.write_record(0, 1, 0xAFF4, signature, wire.now))[0] == 0
    # a wrong length (here: with two bytes of padding after the header), another block type
    status, _ = call(ctl.write_record(0, 1, 0xAFF2, im.block(im.RECORDS[0xAFF2], b"  " +
                                                              b"2026-11-27 05:10"), wire.now))
    assert status == 0xDF80B100  # IODWriteRes, PNIORW, write length error
    wrong = im.block(im.RECORDS[0xAFF1], b" " * 54)
    assert call(ctl.write_record(0, 1, 0xAFF3, wrong, wire.now))[0] == 0xDF80B800
    assert ctl.phase == "data"  # a refused Write leaves the AR as it was
    # what the state file keeps comes back in a device started again
    again = Device(dev.identity, im=dev.im)
    assert again.im[0xAFF1] == written[6:] and again.im[0xAFF4] == bytes(range(54))
