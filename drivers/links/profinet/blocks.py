"""The PNIO blocks of Connect, Control, Release, Read and Write, sans-I/O (IEC 61158-6-10,
"Coding of the fields"): each BlockHeader and body, always big-endian, whichever data
representation the DCE/RPC header around them (:mod:`.rpc`) uses.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Final

from .frames import FrameError

BLOCK_AR_REQ: Final = 0x0101
BLOCK_IOCR_REQ: Final = 0x0102
BLOCK_ALARM_CR_REQ: Final = 0x0103
BLOCK_EXPECTED_SUBMODULE: Final = 0x0104
BLOCK_PRM_END: Final = 0x0110
BLOCK_APP_READY: Final = 0x0112
BLOCK_RELEASE: Final = 0x0114
BLOCK_PRM_BEGIN: Final = 0x0118
BLOCK_READ_REQ: Final = 0x0009
BLOCK_WRITE_REQ: Final = 0x0008
BLOCK_IM0: Final = 0x0020
BLOCK_REAL_IDENTIFICATION: Final = 0x0013
RESPONSE_BIT: Final = 0x8000

CMD_PRM_END: Final = 0x0001
CMD_APP_READY: Final = 0x0002
CMD_RELEASE: Final = 0x0004
CMD_DONE: Final = 0x0008
CMD_PRM_BEGIN: Final = 0x0040

IOCR_INPUT: Final = 1
IOCR_OUTPUT: Final = 2


def block(block_type: int, body: bytes, version: tuple[int, int] = (1, 0)) -> bytes:
    """BlockHeader (BlockType, BlockLength counted after itself, BlockVersion) and body."""
    return struct.pack(">HHBB", block_type, len(body) + 2, *version) + body


def split_blocks(raw: bytes) -> list[tuple[int, bytes]]:
    """(BlockType, body after the version bytes) of each block in ``raw``."""
    out, at = [], 0
    while at < len(raw):
        if at + 6 > len(raw):
            raise FrameError(f"block header cut short at byte {at}")
        btype, blen = struct.unpack_from(">HH", raw, at)
        if blen < 2 or at + 4 + blen > len(raw):
            raise FrameError(f"block 0x{btype:04x} of length {blen} runs past the data")
        out.append((btype, raw[at + 6:at + 4 + blen]))
        at += 4 + blen
    return out


@dataclass(frozen=True)
class ArRequest:
    """ARBlockReq (0x0101)."""

    ar_type: int
    ar_uuid: bytes
    session_key: int
    initiator_mac: bytes
    initiator_object: bytes
    properties: int
    timeout_factor: int
    station_name: str

    @classmethod
    def unpack(cls, body: bytes) -> ArRequest:
        if len(body) < 52:
            raise FrameError(f"ARBlockReq of {len(body)} bytes is too short")
        ar_type, = struct.unpack_from(">H", body, 0)
        session, = struct.unpack_from(">H", body, 18)
        props, tf, _port, nlen = struct.unpack_from(">IHHH", body, 42)
        return cls(ar_type, body[2:18], session, body[20:26], body[26:42], props, tf,
                   body[52:52 + nlen].decode("ascii", "replace"))

    def pack(self) -> bytes:
        """The controller's ARBlockReq (CMInitiatorUDPRTPort 0x8892: RT over Ethernet)."""
        name = self.station_name.encode("ascii")
        return block(BLOCK_AR_REQ, struct.pack(">H", self.ar_type) + self.ar_uuid
                     + struct.pack(">H", self.session_key) + self.initiator_mac
                     + self.initiator_object
                     + struct.pack(">IHHH", self.properties, self.timeout_factor, 0x8892,
                                   len(name)) + name)

    def response(self, responder_mac: bytes) -> bytes:
        return block(BLOCK_AR_REQ | RESPONSE_BIT,
                     struct.pack(">H", self.ar_type) + self.ar_uuid
                     + struct.pack(">H", self.session_key) + responder_mac
                     + struct.pack(">H", 0x8892))


@dataclass(frozen=True)
class IoObject:
    """IODataObject or IOCS of an IOCR: (slot, subslot) at a frame offset."""

    slot: int
    subslot: int
    offset: int


@dataclass(frozen=True)
class IocrRequest:
    """IOCRBlockReq (0x0102), one API (API 0)."""

    iocr_type: int
    reference: int
    properties: int
    data_length: int
    frame_id: int
    send_clock_factor: int
    reduction_ratio: int
    watchdog_factor: int
    data_hold_factor: int
    data: tuple[IoObject, ...] = field(default_factory=tuple)
    iocs: tuple[IoObject, ...] = field(default_factory=tuple)

    @property
    def cycle_us(self) -> float:
        """Send clock × reduction ratio, in µs (the clock unit is 31.25 µs)."""
        return self.send_clock_factor * self.reduction_ratio * 31.25

    @classmethod
    def unpack(cls, body: bytes) -> IocrRequest:
        if len(body) < 40:
            raise FrameError(f"IOCRBlockReq of {len(body)} bytes is too short")
        (itype, ref, _lt, props, dlen, fid, scf, rr, _phase, _seq, _fso, wdf, dhf, _tag
         ) = struct.unpack_from(">HHHIHHHHHHIHHH", body, 0)
        n_apis, = struct.unpack_from(">H", body, 38)
        data: list[IoObject] = []
        iocs: list[IoObject] = []
        at = 40
        try:
            for _ in range(n_apis):
                at += 4
                for target in (data, iocs):
                    n, = struct.unpack_from(">H", body, at)
                    at += 2
                    for _ in range(n):
                        target.append(IoObject(*struct.unpack_from(">HHH", body, at)))
                        at += 6
        except struct.error:
            raise FrameError("IOCRBlockReq's API list runs past the block") from None
        return cls(itype, ref, props, dlen, fid, scf, rr, wdf, dhf, tuple(data), tuple(iocs))

    def pack(self) -> bytes:
        """The controller's IOCRBlockReq: LT 0x8892, phase 1, FrameSendOffset 0xFFFFFFFF (as
        soon as possible), VLAN priority 6, no multicast address, API 0."""
        body = struct.pack(">HHHIHHHHHHIHHH", self.iocr_type, self.reference, 0x8892,
                           self.properties, self.data_length, self.frame_id,
                           self.send_clock_factor, self.reduction_ratio, 1, 0, 0xFFFFFFFF,
                           self.watchdog_factor, self.data_hold_factor, 0xC000)
        body += bytes(6) + struct.pack(">HI", 1, 0)
        for objs in (self.data, self.iocs):
            body += struct.pack(">H", len(objs)) + b"".join(
                struct.pack(">HHH", o.slot, o.subslot, o.offset) for o in objs)
        return block(BLOCK_IOCR_REQ, body)

    def response(self, frame_id: int) -> bytes:
        return block(BLOCK_IOCR_REQ | RESPONSE_BIT,
                     struct.pack(">HHH", self.iocr_type, self.reference, frame_id))


@dataclass(frozen=True)
class AlarmCrRequest:
    """AlarmCRBlockReq (0x0103)."""

    cr_type: int
    lt: int
    properties: int
    timeout_factor: int
    retries: int
    local_reference: int
    max_data_length: int

    @classmethod
    def unpack(cls, body: bytes) -> AlarmCrRequest:
        if len(body) < 20:
            raise FrameError(f"AlarmCRBlockReq of {len(body)} bytes is too short")
        return cls(*struct.unpack_from(">HHIHHHH", body, 0))

    def pack(self) -> bytes:
        """The controller's AlarmCRBlockReq (tag headers: priority 6 high, 5 low)."""
        return block(BLOCK_ALARM_CR_REQ, struct.pack(
            ">HHIHHHHHH", self.cr_type, self.lt, self.properties, self.timeout_factor,
            self.retries, self.local_reference, self.max_data_length, 0xC000, 0xA000))

    def response(self, device_reference: int) -> bytes:
        return block(BLOCK_ALARM_CR_REQ | RESPONSE_BIT,
                     struct.pack(">HHH", self.cr_type, device_reference,
                                 min(self.max_data_length, 200)))


@dataclass(frozen=True)
class ExpectedSubmodule:
    """One submodule of an ExpectedSubmoduleBlockReq (0x0104): where, which idents, and the
    data lengths its DataDescriptions give (input = device → controller)."""

    api: int
    slot: int
    module_ident: int
    subslot: int
    submodule_ident: int
    input_length: int
    output_length: int


def expected_submodules(body: bytes) -> list[ExpectedSubmodule]:
    """The submodules an ExpectedSubmoduleBlockReq body lists."""
    out: list[ExpectedSubmodule] = []
    try:
        n_apis, = struct.unpack_from(">H", body, 0)
        at = 2
        for _ in range(n_apis):
            api, slot, mident, _mprops, n_sub = struct.unpack_from(">IHIHH", body, at)
            at += 14
            for _ in range(n_sub):
                subslot, sident, sprops = struct.unpack_from(">HIH", body, at)
                at += 8
                lengths = {1: 0, 2: 0}
                for _ in range(2 if sprops & 3 == 3 else 1):
                    desc, dlen, _iocs, _iops = struct.unpack_from(">HHBB", body, at)
                    at += 6
                    lengths[desc] = dlen
                out.append(ExpectedSubmodule(api, slot, mident, subslot, sident,
                                             lengths[1], lengths[2]))
    except struct.error:
        raise FrameError("ExpectedSubmoduleBlockReq runs past its block") from None
    return out


def expected_submodules_block(subs: list[ExpectedSubmodule]) -> bytes:
    """An ExpectedSubmoduleBlockReq (0x0104) listing ``subs``, one entry per (API, slot);
    SubmoduleProperties.Type from the lengths (no IO, input, output, both), IOCS and IOPS of
    one byte each."""
    slots: dict[tuple[int, int], list[ExpectedSubmodule]] = {}
    for s in subs:
        slots.setdefault((s.api, s.slot), []).append(s)
    body = struct.pack(">H", len(slots))
    for (api, slot), group in slots.items():
        body += struct.pack(">IHIHH", api, slot, group[0].module_ident, 0, len(group))
        for s in group:
            kind = (1 if s.input_length else 0) | (2 if s.output_length else 0)
            body += struct.pack(">HIH", s.subslot, s.submodule_ident, kind)
            if kind != 2:  # no IO data is described as an input of length 0
                body += struct.pack(">HHBB", 1, s.input_length, 1, 1)
            if kind & 2:
                body += struct.pack(">HHBB", 2, s.output_length, 1, 1)
    return block(BLOCK_EXPECTED_SUBMODULE, body)


@dataclass(frozen=True)
class ConnectResponse:
    """What a device's Connect response says: its MAC (ARBlockRes), the frame id of each IOCR
    by reference (IOCRBlockRes), its alarm reference (AlarmCRBlockRes) and the rows of a
    ModuleDiffBlock, if any (api, slot, module state, subslot, submodule state)."""

    device_mac: bytes
    frame_ids: dict[int, int]
    alarm_reference: int
    diff: tuple[tuple[int, int, int, int, int], ...]

    @classmethod
    def unpack(cls, body: bytes) -> ConnectResponse:
        mac, alarm_ref = b"", 0
        frame_ids: dict[int, int] = {}
        diff: list[tuple[int, int, int, int, int]] = []
        try:
            for btype, b in split_blocks(body):
                if btype == BLOCK_AR_REQ | RESPONSE_BIT:
                    mac = b[20:26]
                elif btype == BLOCK_IOCR_REQ | RESPONSE_BIT:
                    _t, ref, fid = struct.unpack_from(">HHH", b, 0)
                    frame_ids[ref] = fid
                elif btype == BLOCK_ALARM_CR_REQ | RESPONSE_BIT:
                    alarm_ref, = struct.unpack_from(">H", b, 2)
                elif btype == 0x8104:
                    diff += _module_diff_rows(b)
        except struct.error:
            raise FrameError("Connect response's blocks run past their data") from None
        if len(mac) != 6:
            raise FrameError("Connect response without an ARBlockRes")
        return cls(mac, frame_ids, alarm_ref, tuple(diff))


def _module_diff_rows(b: bytes) -> list[tuple[int, int, int, int, int]]:
    rows = []
    n_apis, = struct.unpack_from(">H", b, 0)
    at = 2
    for _ in range(n_apis):
        api, n_mods = struct.unpack_from(">IH", b, at)
        at += 6
        for _ in range(n_mods):
            slot, _mident, mstate, n_subs = struct.unpack_from(">HIHH", b, at)
            at += 10
            for _ in range(n_subs):
                subslot, _sident, sstate = struct.unpack_from(">HIH", b, at)
                at += 8
                rows.append((api, slot, mstate, subslot, sstate))
    return rows


# ModuleState / SubmoduleState (IEC 61158-6-10, "ModuleDiffBlock")
MODULE_NO: Final = 0
MODULE_WRONG: Final = 1
MODULE_PROPER: Final = 2
SUBMODULE_OK: Final = 0x8000
SUBMODULE_WRONG: Final = 0x8000 | 2 << 11
SUBMODULE_NO: Final = 0x8000 | 3 << 11


def module_diff(rows: list[tuple[int, int, int, int, int, int, int]]) -> bytes:
    """ModuleDiffBlock (0x8104) from (api, slot, module ident, module state, subslot,
    submodule ident, submodule state) rows, grouped by API and slot."""
    apis: dict[int, dict[int, tuple[int, int, list[tuple[int, int, int]]]]] = {}
    for api, slot, mident, mstate, subslot, sident, sstate in rows:
        mods = apis.setdefault(api, {})
        entry = mods.setdefault(slot, (mident, mstate, []))
        entry[2].append((subslot, sident, sstate))
    body = struct.pack(">H", len(apis))
    for api, mods in apis.items():
        body += struct.pack(">IH", api, len(mods))
        for slot, (mident, mstate, subs) in mods.items():
            body += struct.pack(">HIHH", slot, mident, mstate, len(subs))
            for subslot, sident, sstate in subs:
                body += struct.pack(">HIH", subslot, sident, sstate)
    return block(0x8104, body)


@dataclass(frozen=True)
class Control:
    """IODControlReq/Res and IODReleaseReq/Res (0x0110, 0x0112, 0x0114, 0x0118 and their
    responses): ARUUID, SessionKey, ControlCommand."""

    block_type: int
    ar_uuid: bytes
    session_key: int
    command: int
    properties: int = 0

    def pack(self) -> bytes:
        return block(self.block_type, struct.pack(">H", 0) + self.ar_uuid
                     + struct.pack(">HHHH", self.session_key, 0, self.command, self.properties))

    @classmethod
    def unpack(cls, btype: int, body: bytes) -> Control:
        if len(body) < 26:
            raise FrameError(f"control block 0x{btype:04x} of {len(body)} bytes is too short")
        session, _r, cmd, props = struct.unpack_from(">HHHH", body, 18)
        return cls(btype, body[2:18], session, cmd, props)


def record_data(body: bytes) -> bytes:
    """The record data after an IODReadResHeader (0x8009) or IODWriteResHeader (0x8008)."""
    btype, blen = struct.unpack_from(">HH", body, 0) if len(body) >= 4 else (0, 0)
    if btype not in (BLOCK_READ_REQ | RESPONSE_BIT, BLOCK_WRITE_REQ | RESPONSE_BIT) \
            or 4 + blen > len(body):
        raise FrameError(f"record response without its header (block 0x{btype:04x})")
    return body[4 + blen:]


@dataclass(frozen=True)
class RecordRequest:
    """IODReadReqHeader (0x0009) or IODWriteReqHeader (0x0008), and a Write's record data."""

    block_type: int
    seq: int
    ar_uuid: bytes
    api: int
    slot: int
    subslot: int
    index: int
    length: int
    data: bytes = b""

    @classmethod
    def unpack(cls, raw: bytes) -> RecordRequest:
        if len(raw) < 64:
            raise FrameError(f"record request of {len(raw)} bytes is shorter than its header")
        btype, blen = struct.unpack_from(">HH", raw, 0)
        if btype not in (BLOCK_READ_REQ, BLOCK_WRITE_REQ):
            raise FrameError(f"block 0x{btype:04x} is not an IODRead/WriteReqHeader")
        seq, = struct.unpack_from(">H", raw, 6)
        api, slot, subslot, _pad, index, length = struct.unpack_from(">IHHHHI", raw, 24)
        data = raw[4 + blen:4 + blen + length] if btype == BLOCK_WRITE_REQ else b""
        return cls(btype, seq, raw[8:24], api, slot, subslot, index, length, data)

    def pack(self) -> bytes:
        """The controller's request: the header (RWPadding for TargetARUUID and the rest),
        then a Write's record data."""
        return block(self.block_type, struct.pack(">H", self.seq) + self.ar_uuid
                     + struct.pack(">IHHHHI", self.api, self.slot, self.subslot, 0, self.index,
                                   self.length) + bytes(24)) + self.data

    def response(self, length: int, status: int = 0) -> bytes:
        head = (struct.pack(">H", self.seq) + self.ar_uuid
                + struct.pack(">IHHHHIHH", self.api, self.slot, self.subslot, 0, self.index,
                              length, 0, 0))
        if self.block_type == BLOCK_WRITE_REQ:
            head += struct.pack(">I", status) + bytes(16)
        else:
            head += bytes(20)
        return block(self.block_type | RESPONSE_BIT, head)
