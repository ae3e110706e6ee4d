"""Diagnosis alarms over the AR's AlarmCR, sans-I/O: the RTA-PDU (acyclic real-time, frame ids
0xFC01 high / 0xFE01 low priority) with its window of one, transport ACKs and retries, and the
AlarmNotification-PDU with one ChannelDiagnosis item (IEC 61158-6-10, "RTA", "Alarm
notification", "ChannelDiagnosis").

A station alarm (a camera or the station down) appears as a diagnosis alarm on the result
submodule, and disappears (alarm type "diagnosis disappears") when it clears.
"""

from __future__ import annotations

import struct
from collections import deque
from dataclasses import dataclass, field
from typing import Final

from . import blocks
from . import frames as fr
from . import modules as mod

PDU_DATA: Final = 0x11  # version 1, type DATA
PDU_NACK: Final = 0x12
PDU_ACK: Final = 0x13
PDU_ERR: Final = 0x14
ADD_FLAGS_DATA: Final = 0x11  # window size 1, TACK
ADD_FLAGS_ACK: Final = 0x01
SEQ_INIT: Final = 0xFFFF
SEQ_INIT_O: Final = 0xFFFE
SEQ_MASK: Final = 0x7FFF
ALARM_DIAGNOSIS: Final = 0x0001
ALARM_DIAGNOSIS_DISAPPEARS: Final = 0x000C
USI_CHANNEL_DIAGNOSIS: Final = 0x8000
WHOLE_SUBMODULE: Final = 0x8000  # ChannelNumber: the submodule as a whole
# ChannelErrorType: 0x0100..0x7FFF are the manufacturer's (the GSDML could name them)
ERROR_CAMERA_DOWN: Final = 0x0100
ERROR_STATION_DOWN: Final = 0x0101


def next_seq(seq: int) -> int:
    return (seq + 1) & SEQ_MASK


@dataclass(frozen=True)
class Rta:
    """RTA-PDU header: AlarmDstEndpoint, AlarmSrcEndpoint, PDUType, AddFlags, SendSeqNum,
    AckSeqNum, VarPartLen, then the var part."""

    dst_ref: int
    src_ref: int
    pdu_type: int
    add_flags: int
    send_seq: int
    ack_seq: int
    var: bytes = b""

    def pack(self) -> bytes:
        return struct.pack(">HHBBHHH", self.dst_ref, self.src_ref, self.pdu_type,
                           self.add_flags, self.send_seq, self.ack_seq, len(self.var)) + self.var

    @classmethod
    def unpack(cls, raw: bytes) -> Rta:
        if len(raw) < 12:
            raise fr.FrameError(f"RTA-PDU of {len(raw)} bytes is shorter than its header")
        dst, src, ptype, flags, send, ack, n = struct.unpack_from(">HHBBHHH", raw, 0)
        if 12 + n > len(raw):
            raise fr.FrameError(f"RTA VarPartLen {n} runs past the frame")
        return cls(dst, src, ptype, flags, send, ack, raw[12:12 + n])


def notification(appears: bool, error_type: int, seq: int, high: bool,
                 sub: mod.Submodule = mod.RESULT) -> bytes:
    """AlarmNotification-PDU (block 0x0001 high / 0x0002 low) with one ChannelDiagnosis."""
    specifier = (seq & 0x07FF) | 0x0800 | (0x2000 | 0x8000 if appears else 0)
    props = (1 if appears else 2) << 11  # ChannelProperties.Specifier: appears / disappears
    body = struct.pack(">HIHHIIH", ALARM_DIAGNOSIS if appears else ALARM_DIAGNOSIS_DISAPPEARS,
                       mod.API, sub.slot, sub.subslot, sub.module_ident, sub.submodule_ident,
                       specifier)
    body += struct.pack(">HHHH", USI_CHANNEL_DIAGNOSIS, WHOLE_SUBMODULE, props, error_type)
    return blocks.block(0x0001 if high else 0x0002, body)


@dataclass
class AlarmCr:
    """One AR's alarm endpoint: our sequence numbers, the one DATA in flight, the queue."""

    controller_mac: bytes
    own_mac: bytes
    controller_ref: int
    device_ref: int
    high: bool
    timeout_s: float
    retries: int
    send_seq: int = SEQ_INIT
    exp_seq: int = SEQ_INIT  # the controller's next DATA
    exp_seq_o: int = SEQ_INIT_O
    alarm_seq: int = 0
    pending: bytes | None = None
    pending_at: float = 0.0
    tries: int = 0
    queue: deque[bytes] = field(default_factory=deque)
    sent: int = 0
    acked: int = 0
    lost: int = 0

    @property
    def frame_id(self) -> int:
        return fr.FRAME_ID_ALARM_HIGH if self.high else fr.FRAME_ID_ALARM_LOW

    def _frame(self, rta: Rta) -> bytes:
        return fr.Ethernet(self.controller_mac, self.own_mac, fr.ETHERTYPE_PN,
                           struct.pack(">H", self.frame_id) + rta.pack(),
                           vlan_tci=0xC000 if self.high else 0xA000).pack()

    def diagnosis(self, appears: bool, error_type: int, now: float) -> list[bytes]:
        """Queue a diagnosis alarm; the frames to send now."""
        self.queue.append(notification(appears, error_type, self.alarm_seq, self.high))
        self.alarm_seq = (self.alarm_seq + 1) & 0x07FF
        return self._send_next(now)

    def _send_next(self, now: float) -> list[bytes]:
        if self.pending is not None or not self.queue:
            return []
        var = self.queue.popleft()
        self.pending = self._frame(Rta(self.controller_ref, self.device_ref, PDU_DATA,
                                       ADD_FLAGS_DATA, self.send_seq, self.exp_seq_o, var))
        self.pending_at, self.tries = now, 1
        self.sent += 1
        return [self.pending]

    def on_rta(self, rta: Rta, now: float) -> list[bytes]:
        """An RTA-PDU from the controller; the frames to send."""
        if rta.dst_ref != self.device_ref:
            return []
        out: list[bytes] = []
        if self.pending is not None and rta.ack_seq == self.send_seq and \
                rta.pdu_type in (PDU_ACK, PDU_DATA):
            self.pending = None
            self.acked += 1
            self.send_seq = next_seq(self.send_seq)
        if rta.pdu_type == PDU_DATA:
            if rta.send_seq == self.exp_seq:
                self.exp_seq_o, self.exp_seq = self.exp_seq, next_seq(self.exp_seq)
            # an AlarmAck-PDU (or a repeat of one): acknowledge its transport
            out.append(self._frame(Rta(self.controller_ref, self.device_ref, PDU_ACK,
                                       ADD_FLAGS_ACK, self.send_seq, self.exp_seq_o)))
        return out + self._send_next(now)

    def tick(self, now: float) -> list[bytes]:
        """Retransmit the DATA in flight after RTATimeoutFactor × 100 ms, RTARetries times."""
        if self.pending is None or now - self.pending_at < self.timeout_s:
            return []
        if self.tries > self.retries:
            self.pending = None
            self.lost += 1
            self.send_seq = next_seq(self.send_seq)
            return self._send_next(now)
        self.tries += 1
        self.pending_at = now
        return [self.pending]
