"""The PROFINET IO-device, sans-I/O: DCP frames, RPC datagrams and RT frames in, frames,
datagrams and events out, with the clock passed in. Conformance class A, RT_CLASS_1, one IO AR
at a time (IEC 61158-6-10; the AR's life: Connect → parameter phase → PrmEnd →
ApplicationReady (sent by the device, confirmed by the controller) → data exchange; Release or
the data hold time ends it).

This room holds the device's state and routes what comes in: DCP to :mod:`.dcp`, the AR's RPC
operations to :mod:`.relation`, Read and Write to :mod:`.records`, RT frames to
:mod:`.cyclic`, the controller's alarm acknowledgements to :mod:`.alarms`; its clock
(:meth:`Device.tick`) sends the input frames, ApplicationReady and its retries, and ends the AR
when the data hold time passes; station alarms become diagnosis alarms here. The state it
hands back is :mod:`.state`'s.

The transport (:mod:`.transport`) feeds it and sends what it returns; nothing here touches a
socket or reads a clock.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from typing import Final

from .. import layout
from . import cyclic, records, relation, rpc
from . import frames as fr
from . import im as imr
from .alarms import Rta
from .dcp import DcpResponder, Event, Identity, valid_station_name
from .state import Ar, Out, Stats

log = logging.getLogger(__name__)

APP_READY_RETRY_S: Final = 1.0
APP_READY_TRIES: Final = 5


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
        self.device_alarm_ref = 0x0001
        self.diagnoses: dict[str, int] = {}  # active: source → ChannelErrorType

    # ------------------------------------------------------------------ problems

    def bad(self, text: str) -> None:
        """Something malformed or refused: counted, kept among the last errors, logged."""
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
                cyclic.receive_output(self, eth, frame_id, now, out)
            elif (frame_id in (fr.FRAME_ID_ALARM_HIGH, fr.FRAME_ID_ALARM_LOW)
                  and eth.dst == self.identity.mac and self.ar is not None
                  and eth.src == self.ar.controller_mac):
                out.frames += self.ar.alarm.on_rta(Rta.unpack(eth.payload[2:]), now)
            # alarms from the controller (ACKs) and other frame ids: not ours to answer
        except (ValueError, IndexError, struct.error) as err:  # FrameError is a ValueError
            self.bad(f"frame from {fr.mac_text(raw[6:12])} dropped: {err}")
        return out

    # ------------------------------------------------------------------ RPC

    def on_datagram(self, data: bytes, addr: tuple[str, int], now: float) -> Out:
        """One UDP datagram to the RPC port (34964)."""
        out = Out()
        try:
            self._rpc(data, addr, now, out)
        except (ValueError, IndexError, struct.error) as err:  # FrameError is a ValueError
            self.bad(f"RPC datagram from {addr[0]}:{addr[1]} dropped: {err}")
        return out

    def _rpc(self, data: bytes, addr: tuple[str, int], now: float, out: Out) -> None:
        head = rpc.RpcHeader.unpack(data)
        if head.ptype == rpc.RESPONSE and head.interface == rpc.IFACE_CONTROLLER:
            relation.app_ready_confirmed(self, head, data[rpc.HEADER_SIZE:], now, out)
            return
        if head.ptype != rpc.REQUEST:
            return
        if head.interface != rpc.IFACE_DEVICE:
            raise fr.FrameError(f"interface {head.interface} is not the PNIO device's")
        self.stats.rpc_requests += 1
        ndr = rpc.Ndr.unpack(data[rpc.HEADER_SIZE:], head.little)
        handlers = {rpc.OP_CONNECT: relation.connect, rpc.OP_CONTROL: relation.control,
                    rpc.OP_RELEASE: relation.release, rpc.OP_READ: records.read,
                    rpc.OP_READ_IMPLICIT: records.read, rpc.OP_WRITE: records.write}
        handler = handlers.get(head.opnum)
        if handler is None:
            raise fr.FrameError(f"RPC operation {head.opnum} is not a PNIO operation")
        status, body = handler(self, ndr.body, addr, now, out)
        reply = rpc.Ndr(status, body, ndr.first).pack(head.little, response=True)
        resp = rpc.RpcHeader(rpc.RESPONSE, head.object, head.interface, head.activity,
                             head.seqnum, head.opnum, len(reply), head.little, flags1=0x0A,
                             interface_version=head.interface_version, serial=head.serial)
        out.datagrams.append((resp.pack() + reply, addr))

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

    # ------------------------------------------------------------------ time

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
                relation.end(self, out, Event("aborted", "ApplicationReady never confirmed"))
                out.output = self.output_image
                return out
            out.datagrams.append(relation.app_ready_request(ar))
            ar.app_ready_tries += 1
            ar.app_ready_at = now + APP_READY_RETRY_S
        out.frames += ar.alarm.tick(now)
        if now >= ar.next_send:
            out.frames.append(cyclic.input_frame(ar, self.input_image, self.identity.mac))
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
