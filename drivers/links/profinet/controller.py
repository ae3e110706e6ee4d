"""Our own PROFINET IO-controller, sans-I/O: the PLC's side of one IO AR with the station's
device, for the PLC twin of the demo, the tests and the bench (:mod:`.twin` gives it sockets).
It speaks through the same frame, DCP, RPC and block code as the device (:mod:`.frames`,
:mod:`.dcp`, :mod:`.rpc`, :mod:`.blocks`), with the clock passed in.

The AR's life as a controller leads it (IEC 61158-6-10): DCP Identify by NameOfStation →
RPC Connect (ARBlockReq, an input and an output IOCR, AlarmCR, the expected submodules of
:mod:`.modules`) → cyclic output frames from then on → Control PrmEnd → the device's
ApplicationReady, answered → data exchange; Release at the end. The device's diagnosis alarms
are acknowledged (RTA ACK) and reported as events.
"""

from __future__ import annotations

import struct
import uuid
from dataclasses import dataclass, field
from typing import Final

from .. import layout
from . import blocks, rpc
from . import frames as fr
from . import modules as mod
from .alarms import ADD_FLAGS_ACK, PDU_ACK, PDU_DATA, SEQ_INIT, Rta
from .dcp import Event, Identity, found_device, identify_request, set_request, set_result
from .device import Out

SEND_CLOCK_FACTOR: Final = 32  # 1 ms send clock (31.25 µs × 32)
RETRY_S: Final = 1.0  # an unanswered DCP or RPC request goes out again after this
TRIES: Final = 5
APP_READY_WAIT_S: Final = 10.0
INPUT_FRAME_ID: Final = 0xC001  # proposed; the device confirms the input IOCR's frame id
CONTROLLER_DEVICE_ID: Final = 0x0002


@dataclass
class Stats:
    frames_in: int = 0
    frames_out: int = 0
    malformed: int = 0
    alarms: int = 0
    retries: int = 0
    last_errors: list[str] = field(default_factory=list)


@dataclass
class _Pending:
    """A request waiting for its answer: what to send again, where, when."""

    data: bytes
    addr: tuple[str, int] | None  # None: an Ethernet frame
    at: float
    tries: int = 1


def _layout(subs: tuple[mod.Submodule, ...], rr: int, hold: int
            ) -> tuple[blocks.IocrRequest, blocks.IocrRequest]:
    """Both IOCRs (RT_CLASS_1, send clock × ``rr``, data hold ``hold`` cycles) and their frame
    offsets: in the input CR the data of every submodule that is not an output (with its IOPS),
    then an IOCS per output submodule; in the output CR the reverse. The C_SDU is at least 40
    bytes (RT_CLASS_1's minimum)."""
    ins = [s for s in subs if not s.output_length]
    outs = [s for s in subs if s.output_length]

    def iocr(kind: int, data: list[mod.Submodule], iocs: list[mod.Submodule], frame_id: int
             ) -> blocks.IocrRequest:
        at, d, c = 0, [], []
        for s in data:
            d.append(blocks.IoObject(s.slot, s.subslot, at))
            at += (s.output_length if kind == blocks.IOCR_OUTPUT else s.input_length) + 1
        for s in iocs:
            c.append(blocks.IoObject(s.slot, s.subslot, at))
            at += 1
        return blocks.IocrRequest(kind, kind, 1, max(40, at), frame_id, SEND_CLOCK_FACTOR, rr,
                               hold, hold, tuple(d), tuple(c))

    return (iocr(blocks.IOCR_INPUT, ins, outs, INPUT_FRAME_ID),
            iocr(blocks.IOCR_OUTPUT, outs, ins, 0xFFFF))


class Controller:
    """The IO-controller's protocol state for one device named ``station_name``.
    ``output_image`` is the layout's OUTPUT block (big-endian) it sends every cycle;
    ``input_image`` the INPUT block the device last sent. Events: found, connected (with a
    ModuleDiff: ``module_diff``), running, alarm, released, lost, failed, set, record (a
    Read or Write answered: ``record`` holds its PNIOStatus and data)."""

    def __init__(self, mac: bytes, station_name: str, *, cycle_ms: float = 4.0,
                 data_hold_factor: int = 3, own_name: str = "mvpose-plc-twin",
                 submodules: tuple[mod.Submodule, ...] = mod.SUBMODULES) -> None:
        rr = round(cycle_ms * 1000 / (SEND_CLOCK_FACTOR * 31.25))
        if not 1 <= rr <= 512 or abs(rr * SEND_CLOCK_FACTOR * 31.25 - cycle_ms * 1000) > 1e-6:
            raise ValueError(f"PROFINET cycle {cycle_ms} ms is not a whole number of 1 ms "
                             "send clocks from 1 to 512")
        if not 1 <= data_hold_factor <= 0x1E00:
            raise ValueError(f"data hold factor {data_hold_factor} is not 1..7680")
        self.mac = mac
        self.station_name = station_name
        self.submodules = submodules
        self.input_cr, self.output_cr = _layout(submodules, rr, data_hold_factor)
        self.period_s = cycle_ms / 1000
        self.hold_s = data_hold_factor * self.period_s
        self.ar_uuid = uuid.uuid4().bytes
        self.session_key = 1
        self.own_name = own_name
        self.object = rpc.object_uuid(1, CONTROLLER_DEVICE_ID, 0xFFFF)
        self.stats = Stats()
        self.phase = "idle"  # identify → connect → prm_end → app_ready → data; released, failed
        self.device: Identity | None = None
        self.device_addr: tuple[str, int] = ("", rpc.RPC_PORT)
        self.diff: tuple[tuple[int, int, int, int, int], ...] = ()
        self.output_image = bytes(layout.OUTPUT_SIZE)
        self.input_image = bytes(layout.INPUT_SIZE)
        self.input_frame_id = INPUT_FRAME_ID
        self.output_frame_id = 0
        self.alarm_ref = 0x0001  # ours
        self.device_alarm_ref = 0
        self._alarm_acked: int | None = None  # the last alarm DATA's SendSeqNum
        self._xid = 0x4D560000
        self._seq = 0
        self._activity = uuid.uuid4()
        self._pending: _Pending | None = None
        self._next_send = 0.0
        self._cycle = 0
        self._last_input: float | None = None
        self._since = 0.0
        self.data_status_in = 0
        self.record: tuple[int, bytes] | None = None  # the last Read/Write: status, data

    # ------------------------------------------------------------------ the user's calls

    def start(self, now: float) -> Out:
        """Look for the device by name (DCP Identify); the AR follows by itself."""
        out = Out()
        self.phase, self._since = "identify", now
        self._xid += 1
        self._send(out, identify_request(self.mac, self._xid, self.station_name), None, now)
        return out

    def set_name(self, device_mac: bytes, name: str, now: float) -> Out:
        """DCP Set NameOfStation of the device at ``device_mac`` (before an AR)."""
        return self._set(device_mac, fr.Opt.NAME_OF_STATION, name.encode("ascii"), now)

    def set_ip(self, device_mac: bytes, ip: tuple[bytes, bytes, bytes], now: float) -> Out:
        """DCP Set IP (address, mask, gateway) of the device at ``device_mac``."""
        return self._set(device_mac, fr.Opt.IP_PARAMETER, b"".join(ip), now)

    def read_record(self, slot: int, subslot: int, index: int, now: float) -> Out:
        """RPC Read of record ``index`` (e.g. 0xAFF0..0xAFF4, I&M0..4) within the AR."""
        req = blocks.RecordRequest(blocks.BLOCK_READ_REQ, self._seq, self.ar_uuid, mod.API, slot,
                                subslot, index, 4096)
        return self._record_call(rpc.OP_READ, req, now)

    def write_record(self, slot: int, subslot: int, index: int, data: bytes,
                     now: float) -> Out:
        """RPC Write of ``data`` to record ``index`` within the AR."""
        req = blocks.RecordRequest(blocks.BLOCK_WRITE_REQ, self._seq, self.ar_uuid, mod.API, slot,
                                subslot, index, len(data), data)
        return self._record_call(rpc.OP_WRITE, req, now)

    def _record_call(self, opnum: int, req: blocks.RecordRequest, now: float) -> Out:
        if self.phase not in ("app_ready", "data") or self._pending is not None:
            raise RuntimeError(f"a record call needs an AR without a request in flight "
                               f"(phase {self.phase})")
        out = Out()
        self.record = None
        self._rpc(out, opnum, req.pack(), now)
        return out

    def release(self, now: float) -> Out:
        """End the AR (RPC Release); the cyclic frames stop at once."""
        out = Out()
        if self.phase in ("prm_end", "app_ready", "data"):
            body = blocks.Control(blocks.BLOCK_RELEASE, self.ar_uuid, self.session_key,
                               blocks.CMD_RELEASE).pack()
            self._rpc(out, rpc.OP_RELEASE, body, now)
        self.phase = "released"
        return out

    # ------------------------------------------------------------------ Ethernet in

    def on_frame(self, raw: bytes, now: float) -> Out:
        out = Out()
        try:
            eth = fr.Ethernet.unpack(raw)
            if eth.ethertype != fr.ETHERTYPE_PN or eth.dst not in (self.mac, fr.DCP_MULTICAST) \
                    or eth.src == self.mac or len(eth.payload) < 2:
                return out
            (frame_id,) = struct.unpack_from(">H", eth.payload, 0)
            if frame_id == fr.FRAME_ID_DCP_IDENTIFY_RES:
                self._found(eth, now, out)
            elif frame_id == fr.FRAME_ID_DCP_GET_SET:
                error = set_result(eth, self._xid)
                if error is not None:
                    self._pending = None
                    out.events.append(Event("set", f"DCP Set to {fr.mac_text(eth.src)}: "
                                            + ("done" if error == fr.BLOCK_OK
                                               else f"refused (BlockError {error})")))
            elif frame_id == self.input_frame_id and self.device is not None \
                    and eth.src == self.device.mac:
                self._rt(eth, now, out)
            elif frame_id in (fr.FRAME_ID_ALARM_HIGH, fr.FRAME_ID_ALARM_LOW) \
                    and self.device is not None and eth.src == self.device.mac:
                self._alarm(Rta.unpack(eth.payload[2:]), frame_id, out)
        except (ValueError, IndexError, struct.error) as err:  # FrameError is a ValueError
            self._bad(f"frame from {fr.mac_text(raw[6:12])} dropped: {err}")
        return out

    def _found(self, eth: fr.Ethernet, now: float, out: Out) -> None:
        found = found_device(eth)
        if self.phase != "identify" or found is None or found.station_name != self.station_name:
            return
        if not any(found.ip[0]):
            self._fail(out, f"device {self.station_name!r} ({fr.mac_text(found.mac)}) has no "
                       "IP address: set one (DCP Set IP) or give its interface one")
            return
        self.device = found
        self.device_addr = (".".join(str(b) for b in found.ip[0]), rpc.RPC_PORT)
        out.events.append(Event("found", f"{self.station_name!r} at {fr.mac_text(found.mac)}, "
                                f"{self.device_addr[0]}"))
        self.phase, self._since = "connect", now
        self._pending = None
        ar = blocks.ArRequest(0x0001, self.ar_uuid, self.session_key, self.mac,
                           self.object.bytes, 0x00000011, 100, self.own_name)
        alarm = blocks.AlarmCrRequest(1, 0x8892, 0, 1, 3, self.alarm_ref, 200)
        expected = [blocks.ExpectedSubmodule(mod.API, s.slot, s.module_ident, s.subslot,
                                          s.submodule_ident, s.input_length, s.output_length)
                    for s in self.submodules]
        body = (ar.pack() + self.input_cr.pack() + self.output_cr.pack() + alarm.pack()
                + blocks.expected_submodules_block(expected))
        self._rpc(out, rpc.OP_CONNECT, body, now)

    # ------------------------------------------------------------------ RPC

    def on_datagram(self, data: bytes, addr: tuple[str, int], now: float) -> Out:
        out = Out()
        try:
            head = rpc.RpcHeader.unpack(data)
            if head.ptype == rpc.REQUEST and head.interface == rpc.IFACE_CONTROLLER:
                self._app_ready(head, data[rpc.HEADER_SIZE:], addr, now, out)
            elif head.ptype == rpc.RESPONSE and head.interface == rpc.IFACE_DEVICE \
                    and head.activity == self._activity and self._pending is not None:
                self._pending = None
                ndr = rpc.Ndr.unpack(data[rpc.HEADER_SIZE:], head.little, response=True)
                self._answer(head.opnum, ndr.first, ndr.body, now, out)
        except (ValueError, IndexError, struct.error) as err:
            self._bad(f"RPC datagram from {addr[0]}:{addr[1]} dropped: {err}")
        return out

    def _answer(self, opnum: int, status: int, body: bytes, now: float, out: Out) -> None:
        if opnum in (rpc.OP_READ, rpc.OP_WRITE):
            self.record = (status, blocks.record_data(body) if status == 0 else b"")
            what = "Read" if opnum == rpc.OP_READ else "Write"
            out.events.append(Event("record", f"{what} " + (
                "done" if status == 0 else f"refused: PNIOStatus 0x{status:08x}")))
            return
        if status != 0:
            what = {rpc.OP_CONNECT: "Connect", rpc.OP_CONTROL: "PrmEnd",
                    rpc.OP_RELEASE: "Release"}.get(opnum, f"operation {opnum}")
            self._fail(out, f"{what} refused by {self.station_name!r}: PNIOStatus "
                       f"0x{status:08x}")
            return
        if opnum == rpc.OP_CONNECT and self.phase == "connect":
            res = blocks.ConnectResponse.unpack(body)
            self.input_frame_id = res.frame_ids.get(self.input_cr.reference, INPUT_FRAME_ID)
            self.output_frame_id = res.frame_ids.get(self.output_cr.reference, 0)
            self.device_alarm_ref = res.alarm_reference
            self.diff = res.diff
            out.events.append(Event("connected", f"AR with {self.station_name!r}, cycle "
                                    f"{self.period_s * 1000:g} ms" + (
                                        f", {len(res.diff)} submodules differ (ModuleDiff)"
                                        if res.diff else "")))
            self.phase, self._next_send = "prm_end", now
            ctl = blocks.Control(blocks.BLOCK_PRM_END, self.ar_uuid, self.session_key,
                              blocks.CMD_PRM_END).pack()
            self._rpc(out, rpc.OP_CONTROL, ctl, now)
        elif opnum == rpc.OP_CONTROL and self.phase == "prm_end":
            self.phase, self._since = "app_ready", now
        elif opnum == rpc.OP_RELEASE:
            out.events.append(Event("released", f"AR with {self.station_name!r} released"))

    def _app_ready(self, head: rpc.RpcHeader, body: bytes, addr: tuple[str, int], now: float,
                   out: Out) -> None:
        ndr = rpc.Ndr.unpack(body, head.little)
        btype, b = blocks.split_blocks(ndr.body)[0]
        ctl = blocks.Control.unpack(btype, b)
        ours = ctl.ar_uuid == self.ar_uuid and ctl.session_key == self.session_key
        status = 0 if ours and ctl.command == blocks.CMD_APP_READY else \
            rpc.pnio_status(0xDD, 0x81, 0x3F, 0x05)  # unknown AR
        reply = blocks.Control(btype | blocks.RESPONSE_BIT, ctl.ar_uuid, ctl.session_key,
                            blocks.CMD_DONE).pack()
        out.datagrams.append((rpc.response(head, status, reply), addr))
        if status == 0 and self.phase in ("prm_end", "app_ready"):
            self.phase, self._since = "data", now
            out.events.append(Event("running", "ApplicationReady answered: data exchange"))

    # ------------------------------------------------------------------ cyclic data

    def _rt(self, eth: fr.Ethernet, now: float, out: Out) -> None:
        frame = fr.RtFrame.unpack(eth.payload, self.input_cr.data_length)
        self.stats.frames_in += 1
        self.data_status_in = frame.data_status
        if not frame.data_status & fr.DATA_STATUS_VALID:
            return
        self._last_input = now
        image = bytearray(self.input_image)
        for obj in self.input_cr.data:
            sub = mod.find(obj.slot, obj.subslot)
            if sub is None or not sub.input_length:
                continue
            lo, n = sub.input
            if frame.c_sdu[obj.offset + n] & fr.IOXS_GOOD:  # the device's IOPS
                image[lo:lo + n] = frame.c_sdu[obj.offset:obj.offset + n]
        if bytes(image) != self.input_image:
            self.input_image = bytes(image)
            out.output = self.input_image

    def _output_frame(self) -> bytes:
        sdu = bytearray(self.output_cr.data_length)
        for obj in self.output_cr.data:
            sub = mod.find(obj.slot, obj.subslot)
            if sub is None:
                continue
            lo, n = sub.output
            sdu[obj.offset:obj.offset + n] = self.output_image[lo:lo + n]
            sdu[obj.offset + n] = fr.IOXS_GOOD  # our IOPS
        for obj in self.output_cr.iocs:
            sdu[obj.offset] = fr.IOXS_GOOD  # our IOCS for the device's data
        self._cycle = (self._cycle + SEND_CLOCK_FACTOR * self.output_cr.reduction_ratio) \
            & 0xFFFF
        rt = fr.RtFrame(self.output_frame_id, bytes(sdu), self._cycle, fr.DATA_STATUS_GOOD)
        assert self.device is not None
        return fr.Ethernet(self.device.mac, self.mac, fr.ETHERTYPE_PN, rt.pack(),
                           vlan_tci=0xC000).pack()

    def _alarm(self, rta: Rta, frame_id: int, out: Out) -> None:
        if rta.dst_ref != self.alarm_ref or rta.pdu_type != PDU_DATA:
            return
        if rta.send_seq != self._alarm_acked:  # a repeat is acknowledged again, not counted
            self.stats.alarms += 1
            self._alarm_acked = rta.send_seq
            kind = "appears" if len(rta.var) > 6 and rta.var[7] == 0x01 else "disappears"
            # AlarmNotification: block header (6), AlarmType, API, SlotNumber
            slot = struct.unpack_from(">H", rta.var, 12)[0] if len(rta.var) >= 14 else -1
            out.events.append(Event("alarm", f"diagnosis {kind} on slot {slot}"))
        ack = Rta(self.device_alarm_ref, self.alarm_ref, PDU_ACK, ADD_FLAGS_ACK,
                  SEQ_INIT, rta.send_seq)  # we send no alarms: our SendSeqNum stays initial
        assert self.device is not None
        out.frames.append(fr.Ethernet(self.device.mac, self.mac, fr.ETHERTYPE_PN,
                                      struct.pack(">H", frame_id) + ack.pack(),
                                      vlan_tci=0xA000).pack())

    # ------------------------------------------------------------------ time

    def tick(self, now: float) -> Out:
        """Time passed: the output frame when due, requests again, the input's data hold."""
        out = Out()
        p = self._pending
        if p is not None and now - p.at >= RETRY_S:
            if p.tries >= TRIES:
                self._pending = None
                self._fail(out, f"{self.station_name!r} did not answer "
                           + ("DCP Identify" if self.phase == "identify" else
                              f"in phase {self.phase}") + f" ({TRIES} tries)")
                return out
            p.tries, p.at = p.tries + 1, now
            self.stats.retries += 1
            if p.addr is None:
                out.frames.append(p.data)
            else:
                out.datagrams.append((p.data, p.addr))
        if self.phase == "app_ready" and now - self._since > APP_READY_WAIT_S:
            self._fail(out, f"{self.station_name!r} sent no ApplicationReady")
        last = self._last_input if self._last_input is not None else self._since
        if self.phase == "data" and now - max(last, self._since) > self.hold_s:
            self._fail(out, f"no input frame from {self.station_name!r} for "
                       f"{self.hold_s * 1000:g} ms (data hold time)", kind="lost")
        if self.phase in ("prm_end", "app_ready", "data") and now >= self._next_send:
            out.frames.append(self._output_frame())
            out.cyclic = True
            self.stats.frames_out += 1
            self._next_send = max(self._next_send + self.period_s, now - self.period_s)
        return out

    def next_deadline(self, now: float) -> float:
        """When :meth:`tick` has work next."""
        at = now + 0.1
        if self.phase in ("prm_end", "app_ready", "data"):
            at = min(at, self._next_send)
        if self._pending is not None:
            at = min(at, self._pending.at + RETRY_S)
        return at

    # ------------------------------------------------------------------ helpers

    def _set(self, device_mac: bytes, key: tuple[int, int], value: bytes, now: float) -> Out:
        out = Out()
        self._xid += 1
        self._send(out, set_request(self.mac, device_mac, self._xid, key, value), None, now)
        return out

    def _send(self, out: Out, data: bytes, addr: tuple[str, int] | None, now: float) -> None:
        self._pending = _Pending(data, addr, now)
        if addr is None:
            out.frames.append(data)
        else:
            out.datagrams.append((data, addr))

    def _rpc(self, out: Out, opnum: int, body: bytes, now: float) -> None:
        self._seq += 1
        self._activity = uuid.uuid4()
        assert self.device is not None
        obj = rpc.object_uuid(1, self.device.device_id, self.device.vendor_id)
        self._send(out, rpc.request(obj, self._activity, self._seq, opnum, body),
                   self.device_addr, now)

    def _fail(self, out: Out, text: str, kind: str = "failed") -> None:
        self.phase = "failed"
        self._pending = None
        out.events.append(Event(kind, text))

    def _bad(self, text: str) -> None:
        self.stats.malformed += 1
        self.stats.last_errors = [*self.stats.last_errors[-9:], text]


__all__ = ["Controller", "Stats"]
