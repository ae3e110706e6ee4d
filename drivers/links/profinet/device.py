"""The PROFINET IO-device, sans-I/O: DCP frames, RPC datagrams and RT frames in, frames,
datagrams and events out, with the clock passed in. Conformance class A, RT_CLASS_1, one IO AR
at a time (IEC 61158-6-10; the AR's life: Connect → parameter phase → PrmEnd →
ApplicationReady (sent by the device, confirmed by the controller) → data exchange; Release or
the data hold time ends it).

The transport (:mod:`.transport`) feeds it and sends what it returns; nothing here touches a
socket or reads a clock.
"""

from __future__ import annotations

import logging
import struct
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

from .. import layout
from . import blocks, rpc
from . import frames as fr
from . import im as imr
from . import modules as mod
from .alarms import AlarmCr, Rta
from .dcp import DcpResponder, Event, Identity, valid_station_name

log = logging.getLogger(__name__)

APP_READY_RETRY_S: Final = 1.0
APP_READY_TRIES: Final = 5
REALIGN_AFTER: Final = 8  # output frames off the input phase in a row before it moves


@dataclass
class Stats:
    rpc_requests: int = 0
    frames_in: int = 0
    frames_out: int = 0
    malformed: int = 0
    connects: int = 0
    refused_connects: int = 0
    module_diffs: int = 0
    data_hold_expired: int = 0
    releases: int = 0
    send_errors: int = 0
    last_errors: list[str] = field(default_factory=list)


@dataclass
class Ar:
    """The one application relationship (IO AR) and its two IOCRs."""

    request: blocks.ArRequest
    controller_mac: bytes
    controller_addr: tuple[str, int]
    input_cr: blocks.IocrRequest
    output_cr: blocks.IocrRequest
    input_frame_id: int
    output_frame_id: int
    alarm: AlarmCr
    phase: str = "parameter"  # parameter → ready (ApplicationReady sent) → data
    next_send: float = 0.0
    cycle: int = 0
    last_output: float | None = None
    connected_at: float = 0.0
    app_ready_at: float = 0.0
    app_ready_tries: int = 0
    app_ready_activity: uuid.UUID = field(default_factory=uuid.uuid4)
    off_phase: int = 0  # output frames in a row that came off the input frames' phase
    realigned: int = 0

    @property
    def input_period_s(self) -> float:
        return self.input_cr.cycle_us / 1e6

    @property
    def hold_s(self) -> float:
        """The data hold time: DataHoldFactor × the output IOCR's cycle."""
        return self.output_cr.data_hold_factor * self.output_cr.cycle_us / 1e6


@dataclass
class Out:
    """What one call hands the transport: Ethernet frames, UDP datagrams (data, address),
    events, and a new output image when the controller's outputs changed."""

    frames: list[bytes] = field(default_factory=list)
    datagrams: list[tuple[bytes, tuple[str, int]]] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)
    output: bytes | None = None
    cyclic: bool = False  # ``frames`` holds this cycle's input frame
    im_changed: bool = False  # an I&M record was written: store ``Device.im``


class Device:
    """The IO-device's protocol state. ``input_image`` is the layout's INPUT block (big-endian)
    the station publishes; ``output_image`` the OUTPUT block the controller last sent.
    ``im`` holds the I&M1..4 records' data by index (what the state file kept); ``accept_ip``
    and ``set_ip`` are DCP Set IP's (:class:`~.dcp.DcpResponder`)."""

    def __init__(self, identity: Identity, min_cycle_ms: float = 1.0,
                 input_phase_ms: float | None = None, *, accept_ip: bool = True,
                 set_ip: Callable[[tuple[bytes, bytes, bytes], bool], str | None] | None = None,
                 im: dict[int, bytes] | None = None) -> None:
        self.identity = identity
        self.dcp = DcpResponder(identity, accept_ip, set_ip)
        self.im = {i: imr.default(r) for i, r in imr.RECORDS.items()}
        for index, data in (im or {}).items():
            if index in self.im and len(data) == len(self.im[index]):
                self.im[index] = data
        self.min_cycle_us = min_cycle_ms * 1000
        # None: half the cycle (what a loaded host's station needs to answer within it)
        self.input_phase_s = None if input_phase_ms is None else input_phase_ms / 1000
        self.stats = Stats()
        self.ar: Ar | None = None
        self.input_image = bytes(layout.INPUT_SIZE)
        self.output_image = bytes(layout.OUTPUT_SIZE)
        self.records: dict[tuple[int, int, int], bytes] = {}  # parameter records written
        self._device_alarm_ref = 0x0001
        self.diagnoses: dict[str, int] = {}  # active: source → ChannelErrorType

    # ------------------------------------------------------------------ problems

    def _bad(self, text: str) -> None:
        self.stats.malformed += 1
        self.stats.last_errors = [*self.stats.last_errors[-9:], text]
        log.info("profinet: %s", text)

    # ------------------------------------------------------------------ Ethernet in

    def on_frame(self, raw: bytes, now: float) -> Out:
        """One received Ethernet frame (anything not PROFINET is ignored)."""
        out = Out()
        try:
            eth = fr.Ethernet.unpack(raw)
            if eth.ethertype != fr.ETHERTYPE_PN or eth.src == self.identity.mac:
                return out
            if len(eth.payload) < 2:
                raise fr.FrameError("PROFINET frame without a FrameID")
            (frame_id,) = struct.unpack_from(">H", eth.payload, 0)
            if frame_id in (fr.FRAME_ID_DCP_IDENTIFY_REQ, fr.FRAME_ID_DCP_GET_SET):
                if eth.dst not in (self.identity.mac, fr.DCP_MULTICAST):
                    return out
                self.dcp.handle(eth, self.ar is not None, out)
            elif (fr.FRAME_ID_RTC1_MIN <= frame_id <= fr.FRAME_ID_RTC1_MAX
                  and eth.dst == self.identity.mac):
                self._rt(eth, frame_id, now, out)
            elif (frame_id in (fr.FRAME_ID_ALARM_HIGH, fr.FRAME_ID_ALARM_LOW)
                  and eth.dst == self.identity.mac and self.ar is not None
                  and eth.src == self.ar.controller_mac):
                out.frames += self.ar.alarm.on_rta(Rta.unpack(eth.payload[2:]), now)
            # alarms from the controller (ACKs) and other frame ids: not ours to answer
        except (ValueError, IndexError, struct.error) as err:  # FrameError is a ValueError
            self._bad(f"frame from {fr.mac_text(raw[6:12])} dropped: {err}")
        return out

    # ------------------------------------------------------------------ RPC

    def on_datagram(self, data: bytes, addr: tuple[str, int], now: float) -> Out:
        """One UDP datagram to the RPC port (34964)."""
        out = Out()
        try:
            self._rpc(data, addr, now, out)
        except (ValueError, IndexError, struct.error) as err:  # FrameError is a ValueError
            self._bad(f"RPC datagram from {addr[0]}:{addr[1]} dropped: {err}")
        return out

    def _rpc(self, data: bytes, addr: tuple[str, int], now: float, out: Out) -> None:
        head = rpc.RpcHeader.unpack(data)
        if head.ptype == rpc.RESPONSE and head.interface == rpc.IFACE_CONTROLLER:
            self._app_ready_confirmed(head, data[rpc.HEADER_SIZE:], now, out)
            return
        if head.ptype != rpc.REQUEST:
            return
        if head.interface != rpc.IFACE_DEVICE:
            raise fr.FrameError(f"interface {head.interface} is not the PNIO device's")
        self.stats.rpc_requests += 1
        ndr = rpc.Ndr.unpack(data[rpc.HEADER_SIZE:], head.little)
        handlers = {rpc.OP_CONNECT: self._connect, rpc.OP_CONTROL: self._control,
                    rpc.OP_RELEASE: self._release, rpc.OP_READ: self._read,
                    rpc.OP_READ_IMPLICIT: self._read, rpc.OP_WRITE: self._write}
        handler = handlers.get(head.opnum)
        if handler is None:
            raise fr.FrameError(f"RPC operation {head.opnum} is not a PNIO operation")
        status, body = handler(ndr.body, addr, now, out)
        reply = rpc.Ndr(status, body, ndr.first).pack(head.little, response=True)
        resp = rpc.RpcHeader(rpc.RESPONSE, head.object, head.interface, head.activity,
                             head.seqnum, head.opnum, len(reply), head.little, flags1=0x0A,
                             interface_version=head.interface_version, serial=head.serial)
        out.datagrams.append((resp.pack() + reply, addr))

    def _connect(self, body: bytes, addr: tuple[str, int], now: float,
                 out: Out) -> tuple[int, bytes]:
        parts = blocks.split_blocks(body)
        ar_req = None
        iocrs: list[blocks.IocrRequest] = []
        alarm = None
        expected: list[blocks.ExpectedSubmodule] = []
        for btype, b in parts:
            if btype == blocks.BLOCK_AR_REQ:
                ar_req = blocks.ArRequest.unpack(b)
            elif btype == blocks.BLOCK_IOCR_REQ:
                iocrs.append(blocks.IocrRequest.unpack(b))
            elif btype == blocks.BLOCK_ALARM_CR_REQ:
                alarm = blocks.AlarmCrRequest.unpack(b)
            elif btype == blocks.BLOCK_EXPECTED_SUBMODULE:
                expected += blocks.expected_submodules(b)
        if ar_req is None:
            return self._refuse(addr, "Connect without an ARBlockReq", 1, 0), b""
        inputs = [c for c in iocrs if c.iocr_type == blocks.IOCR_INPUT]
        outputs = [c for c in iocrs if c.iocr_type == blocks.IOCR_OUTPUT]
        if ar_req.ar_type != 0x0001 or len(inputs) != 1 or len(outputs) != 1 or alarm is None:
            return self._refuse(addr, "only an IOCARSingle with one input IOCR, one output "
                                "IOCR and an AlarmCR is served", 1, 4), b""
        if self.ar is not None and self.ar.request.ar_uuid != ar_req.ar_uuid:
            return self._refuse(addr, "an AR is already open", 1, 5), b""
        for cr in (inputs[0], outputs[0]):
            if cr.properties & 0x0F != 1:
                return self._refuse(addr, f"IOCR {cr.reference}: only RT_CLASS_1", 2, 4), b""
            if cr.cycle_us < self.min_cycle_us:
                return self._refuse(addr, f"IOCR {cr.reference}: cycle {cr.cycle_us / 1000} ms "
                                    f"is below {self.min_cycle_us / 1000} ms", 2, 8), b""
            if not cr.data_hold_factor >= 1 or cr.data_length > 1440:
                return self._refuse(addr, f"IOCR {cr.reference}: bad data hold factor or "
                                    "length", 2, 26), b""
        diff = self._diff(expected)
        in_id = inputs[0].frame_id if fr.FRAME_ID_RTC1_MIN <= inputs[0].frame_id <= \
            fr.FRAME_ID_RTC1_MAX else 0xC001
        out_id = 0xC000 + 0x100 + (outputs[0].reference & 0xFF)
        mac = ar_req.initiator_mac
        # diagnosis alarms go low priority (frame id 0xFE01), one in flight, RTA retries
        alarm_cr = AlarmCr(mac, self.identity.mac, alarm.local_reference,
                           self._device_alarm_ref, high=False,
                           timeout_s=max(alarm.timeout_factor, 1) * 0.1,
                           retries=min(max(alarm.retries, 3), 15))
        ar = Ar(ar_req, mac, (addr[0], rpc.RPC_PORT), inputs[0], outputs[0], in_id, out_id,
                alarm_cr, next_send=now, connected_at=now)
        self.ar = ar
        self.stats.connects += 1
        if diff:
            self.stats.module_diffs += 1
        self.output_image = bytes(layout.OUTPUT_SIZE)
        out.events.append(Event("connected", f"AR from {addr[0]} ({ar_req.station_name!r}), "
                                f"cycle {inputs[0].cycle_us / 1000:g} ms, data hold "
                                f"{ar.hold_s * 1000:g} ms"
                                + (f", {len(diff)} submodules differ" if diff else "")))
        body_out = (ar_req.response(self.identity.mac) + inputs[0].response(in_id)
                    + outputs[0].response(out_id) + alarm.response(self._device_alarm_ref))
        if diff:
            body_out += blocks.module_diff(diff)
        return 0, body_out

    def _diff(self, expected: list[blocks.ExpectedSubmodule]
              ) -> list[tuple[int, int, int, int, int, int, int]]:
        rows = []
        for e in expected:
            real = mod.find(e.slot, e.subslot) if e.api == mod.API else None
            if real is None:
                rows.append((e.api, e.slot, 0, blocks.MODULE_NO, e.subslot, 0, blocks.SUBMODULE_NO))
            elif real.module_ident != e.module_ident:
                rows.append((e.api, e.slot, real.module_ident, blocks.MODULE_WRONG, e.subslot,
                             real.submodule_ident, blocks.SUBMODULE_WRONG))
            elif (real.submodule_ident != e.submodule_ident
                  or real.input_length != e.input_length
                  or real.output_length != e.output_length):
                rows.append((e.api, e.slot, real.module_ident, blocks.MODULE_PROPER, e.subslot,
                             real.submodule_ident, blocks.SUBMODULE_WRONG))
        return rows

    def _refuse(self, addr: tuple[str, int], text: str, code1: int, code2: int) -> int:
        self.stats.refused_connects += 1
        self._bad(f"Connect from {addr[0]} refused: {text}")
        return rpc.connect_error(code1, code2)

    def _own(self, ar_uuid: bytes, session: int | None = None) -> bool:
        return self.ar is not None and self.ar.request.ar_uuid == ar_uuid and (
            session is None or self.ar.request.session_key == session)

    def _control(self, body: bytes, addr: tuple[str, int], now: float,
                 out: Out) -> tuple[int, bytes]:
        btype, b = blocks.split_blocks(body)[0]
        ctl = blocks.Control.unpack(btype, b)
        if not self._own(ctl.ar_uuid, ctl.session_key):
            self._bad(f"Control from {addr[0]} for an unknown AR")
            return rpc.pnio_status(0xDD, 0x81, 0x3F, 0x05), b""  # IODControlRes, unknown AR
        assert self.ar is not None
        if btype == blocks.BLOCK_PRM_END and ctl.command == blocks.CMD_PRM_END:
            self.ar.phase = "ready"
            self.ar.app_ready_at = now  # ApplicationReady goes out on the next tick
        elif btype == blocks.BLOCK_PRM_BEGIN and ctl.command == blocks.CMD_PRM_BEGIN:
            self.ar.phase = "parameter"
        elif btype == blocks.BLOCK_RELEASE:
            return self._release(body, addr, now, out)
        else:
            return rpc.pnio_status(0xDD, 0x81, 0x3F, 0x06), b""
        reply = blocks.Control(btype | blocks.RESPONSE_BIT, ctl.ar_uuid, ctl.session_key,
                            blocks.CMD_DONE)
        return 0, reply.pack()

    def _release(self, body: bytes, addr: tuple[str, int], now: float,
                 out: Out) -> tuple[int, bytes]:
        btype, b = blocks.split_blocks(body)[0]
        ctl = blocks.Control.unpack(btype, b)
        if btype != blocks.BLOCK_RELEASE or not self._own(ctl.ar_uuid, ctl.session_key):
            self._bad(f"Release from {addr[0]} for an unknown AR")
            return rpc.pnio_status(0xDE, 0x81, 0x3F, 0x05), b""
        self.stats.releases += 1
        self._end(out, Event("released", f"AR released by {addr[0]}"))
        return 0, blocks.Control(btype | blocks.RESPONSE_BIT, ctl.ar_uuid, ctl.session_key,
                              blocks.CMD_DONE).pack()

    def _end(self, out: Out, event: Event) -> None:
        self.ar = None
        self.output_image = bytes(layout.OUTPUT_SIZE)
        out.events.append(event)

    def _read(self, body: bytes, addr: tuple[str, int], now: float,
              out: Out) -> tuple[int, bytes]:
        req = blocks.RecordRequest.unpack(body)
        data = self._record(req)
        if data is None:
            # ErrorCode 0xDE IODReadRes, ErrorDecode 0x80 PNIORW, access: invalid index
            return rpc.pnio_status(0xDE, 0x80, 0xB0, 0x00), req.response(0)
        return 0, req.response(len(data)) + data

    def _record(self, req: blocks.RecordRequest) -> bytes | None:
        if req.index == 0xAFF0 and req.slot == 0:
            return imr.im0(self.identity)
        if req.index in imr.RECORDS and req.slot == 0:
            return imr.block(imr.RECORDS[req.index], self.im[req.index])
        if req.index == 0xF000:
            return imr.real_identification()
        return self.records.get((req.slot, req.subslot, req.index))

    def _write(self, body: bytes, addr: tuple[str, int], now: float,
               out: Out) -> tuple[int, bytes]:
        req = blocks.RecordRequest.unpack(body)
        sub = mod.find(req.slot, req.subslot)
        # user records (0..0x7FFF) and the port/interface records a controller writes in its
        # parameter phase (0x8000..0xAFFF: PDPortDataCheck, PDInterfaceAdjust, ...) are kept
        if not self._own(req.ar_uuid) or sub is None or req.index >= 0xB000:
            # IODWriteRes, PNIORW, access: invalid slot/subslot or index
            status = rpc.pnio_status(0xDF, 0x80, 0xB2 if sub is None else 0xB0, 0)
            return status, req.response(0, status)
        if req.index in imr.RECORDS:
            return self._write_im(req, addr, out)
        self.records[(req.slot, req.subslot, req.index)] = req.data
        return 0, req.response(len(req.data))

    def _write_im(self, req: blocks.RecordRequest, addr: tuple[str, int],
                  out: Out) -> tuple[int, bytes]:
        record = imr.RECORDS[req.index]
        data, code1 = imr.written(record, req.data) if req.slot == 0 else (None, 0xB2)
        if data is None:
            # IODWriteRes, PNIORW, access: write length error / invalid parameter / slot
            status = rpc.pnio_status(0xDF, 0x80, code1, 0)
            text = (f"I&M{record.number} Write from {addr[0]} refused: {len(req.data)} "
                    f"bytes, ErrorCode1 0x{code1:02X}")
            self.stats.last_errors = [*self.stats.last_errors[-9:], text]
            log.info("profinet: %s", text)
            return status, req.response(0, status)
        self.im[req.index] = data
        out.im_changed = True
        out.events.append(Event("im_written", f"I&M{record.number} written by {addr[0]}"))
        return 0, req.response(len(req.data))

    # ------------------------------------------------------------------ ApplicationReady

    def _app_ready_request(self, ar: Ar) -> tuple[bytes, tuple[str, int]]:
        ctl = blocks.Control(blocks.BLOCK_APP_READY, ar.request.ar_uuid, ar.request.session_key,
                          blocks.CMD_APP_READY).pack()
        ndr = rpc.Ndr(len(ctl), ctl, len(ctl)).pack(True, response=False)
        head = rpc.RpcHeader(rpc.REQUEST, uuid.UUID(bytes=ar.request.initiator_object),
                             rpc.IFACE_CONTROLLER, ar.app_ready_activity, ar.app_ready_tries,
                             rpc.OP_CONTROL, len(ndr), True)
        return head.pack() + ndr, ar.controller_addr

    def _app_ready_confirmed(self, head: rpc.RpcHeader, body: bytes, now: float,
                             out: Out) -> None:
        ar = self.ar
        if ar is None or head.activity != ar.app_ready_activity or ar.phase != "ready":
            return
        ndr = rpc.Ndr.unpack(body, head.little)
        if ndr.first != 0:
            self._bad(f"ApplicationReady refused by the controller: 0x{ndr.first:08x}")
            return
        ar.phase = "data"
        out.events.append(Event("running", "ApplicationReady confirmed: data exchange"))
        for error_type in self.diagnoses.values():  # what is down now, for the new AR
            out.frames += ar.alarm.diagnosis(True, error_type, now)

    # ------------------------------------------------------------------ diagnosis

    def diagnosis(self, source: str, appears: bool, error_type: int, now: float) -> Out:
        """A station alarm (``source``: camera:<id>, station) appeared or cleared: a diagnosis
        alarm to the controller when the AR exchanges data, remembered for the next AR."""
        out = Out()
        known = source in self.diagnoses
        if appears == known:
            return out
        if appears:
            self.diagnoses[source] = error_type
        else:
            error_type = self.diagnoses.pop(source)
        if self.ar is not None and self.ar.phase == "data":
            out.frames += self.ar.alarm.diagnosis(appears, error_type, now)
        out.events.append(Event("diagnosis", f"diagnosis {'appears' if appears else 'disappears'}"
                                f": {source} (channel error type 0x{error_type:04x})"))
        return out

    # ------------------------------------------------------------------ cyclic data

    def _rt(self, eth: fr.Ethernet, frame_id: int, now: float, out: Out) -> None:
        ar = self.ar
        if ar is None or frame_id != ar.output_frame_id or eth.src != ar.controller_mac:
            return
        frame = fr.RtFrame.unpack(eth.payload, ar.output_cr.data_length)
        self.stats.frames_in += 1
        if not frame.data_status & fr.DATA_STATUS_VALID:
            return
        running = bool(frame.data_status & fr.DATA_STATUS_RUN)
        self._phase(ar, now)
        ar.last_output = now
        image = bytearray(layout.OUTPUT_SIZE)
        if running:
            for obj in ar.output_cr.data:
                sub = mod.find(obj.slot, obj.subslot)
                if sub is None or not sub.output_length:
                    continue
                lo, n = sub.output
                end = obj.offset + n
                if end >= len(frame.c_sdu):
                    raise fr.FrameError(f"IO data of slot {obj.slot} runs past the C_SDU")
                if frame.c_sdu[end] & fr.IOXS_GOOD:  # the controller's IOPS
                    image[lo:lo + n] = frame.c_sdu[obj.offset:end]
        data = bytes(image)
        if data != self.output_image:
            self.output_image = data
            out.output = data

    def _phase(self, ar: Ar, now: float) -> None:
        """Keep the input frames ``input_phase_s`` after the controller's output frames
        (FrameSendOffset "best effort" leaves the phase in the cycle to the device): what the
        station answers to an output frame within that time leaves with the next input frame,
        not up to a cycle later. The first output frame sets the phase; it moves again only
        after REALIGN_AFTER frames in a row came more than a quarter cycle off it (a clock
        drift, the controller's restart), not with one late frame."""
        period = ar.input_period_s
        phase = period / 2 if self.input_phase_s is None else self.input_phase_s
        want = now + min(phase, period / 2)
        off = (ar.next_send - want) % period
        if ar.last_output is not None and min(off, period - off) <= period / 4:
            ar.off_phase = 0
            return
        ar.off_phase += 1
        if ar.last_output is None or ar.off_phase >= REALIGN_AFTER:
            ar.next_send, ar.off_phase = want, 0
            ar.realigned += 1

    def _input_frame(self, ar: Ar) -> bytes:
        sdu = bytearray(ar.input_cr.data_length)
        for obj in ar.input_cr.data:
            sub = mod.find(obj.slot, obj.subslot)
            n = 0
            if sub is not None and sub.input_length:
                lo, n = sub.input
                sdu[obj.offset:obj.offset + n] = self.input_image[lo:lo + n]
            if obj.offset + n < len(sdu):
                sdu[obj.offset + n] = fr.IOXS_GOOD  # our IOPS
        for obj in ar.input_cr.iocs:
            if obj.offset < len(sdu):
                sdu[obj.offset] = fr.IOXS_GOOD  # our IOCS for the controller's data
        ar.cycle = (ar.cycle + ar.input_cr.send_clock_factor * ar.input_cr.reduction_ratio) \
            & 0xFFFF
        rt = fr.RtFrame(ar.input_frame_id, bytes(sdu), ar.cycle, fr.DATA_STATUS_GOOD)
        return fr.Ethernet(ar.controller_mac, self.identity.mac, fr.ETHERTYPE_PN, rt.pack(),
                           vlan_tci=0xC000).pack()

    def tick(self, now: float) -> Out:
        """Time passed: the input frame when due, ApplicationReady (and its retries), the data
        hold time. Call it at least once per cycle; ``next_deadline`` says when."""
        out = Out()
        ar = self.ar
        if ar is None:
            return out
        held_since = ar.last_output if ar.last_output is not None else ar.connected_at
        # before the first output frame the controller gets its parameter phase's time
        hold = ar.hold_s if ar.last_output is not None else max(ar.hold_s, 10.0)
        if now - held_since > hold:
            self.stats.data_hold_expired += 1
            # the outputs stay as they were: their heartbeat stops, and the handshake's
            # watchdog reports the PLC lost as it does for a Modbus PLC that went away
            self.ar = None
            out.events.append(Event("data_hold_expired",
                                    f"no output frame from {ar.controller_addr[0]} for "
                                    f"{hold * 1000:g} ms (data hold time): AR aborted"))
            return out
        if ar.phase == "ready" and now >= ar.app_ready_at:
            if ar.app_ready_tries >= APP_READY_TRIES:
                self._end(out, Event("aborted", "ApplicationReady never confirmed"))
                out.output = self.output_image
                return out
            out.datagrams.append(self._app_ready_request(ar))
            ar.app_ready_tries += 1
            ar.app_ready_at = now + APP_READY_RETRY_S
        out.frames += ar.alarm.tick(now)
        if now >= ar.next_send:
            out.frames.append(self._input_frame(ar))
            out.cyclic = True
            self.stats.frames_out += 1
            ar.next_send = max(ar.next_send + ar.input_period_s, now - ar.input_period_s)
        return out

    def next_deadline(self, now: float) -> float:
        """When :meth:`tick` has work next (now + 0.1 s with no AR)."""
        if self.ar is None:
            return now + 0.1
        return min(self.ar.next_send, now + 0.05)


__all__ = ["Ar", "Device", "Event", "Identity", "Out", "Stats", "valid_station_name"]
