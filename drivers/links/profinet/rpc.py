"""PROFINET IO over DCE/RPC (connectionless, UDP 34964), sans-I/O: the RPC header, the NDR
wrapper and the PNIOStatus (IEC 61158-6-10, "RPC"; DCE 1.1 RPC, chapter 12 for the header).
The PNIO blocks the NDR wrapper carries are :mod:`.blocks`.

The RPC header and the NDR wrapper follow the sender's data representation (DREP byte 0:
0x10 little-endian, 0x00 big-endian); the PNIO blocks inside are always big-endian.
"""

from __future__ import annotations

import struct
import uuid
from dataclasses import dataclass
from typing import Final

from .frames import FrameError

RPC_PORT: Final = 34964
HEADER_SIZE: Final = 80
NDR_SIZE: Final = 20

# packet types (DCE 1.1, "PDU types") and operations (IEC 61158-6-10, "RPC operations")
REQUEST: Final = 0
RESPONSE: Final = 2
FAULT: Final = 3
REJECT: Final = 6
OP_CONNECT: Final = 0
OP_RELEASE: Final = 1
OP_READ: Final = 2
OP_WRITE: Final = 3
OP_CONTROL: Final = 4
OP_READ_IMPLICIT: Final = 5

IFACE_DEVICE: Final = uuid.UUID("dea00001-6c97-11d1-8271-00a02442df7d")
IFACE_CONTROLLER: Final = uuid.UUID("dea00002-6c97-11d1-8271-00a02442df7d")
OBJECT_PREFIX: Final = "dea00000-6c97-11d1-8271-"


def object_uuid(instance: int, device_id: int, vendor_id: int) -> uuid.UUID:
    """The PNIO object UUID: DEA00000-6C97-11D1-8271-{instance}{device id}{vendor id}."""
    return uuid.UUID(f"{OBJECT_PREFIX}{instance:04x}{device_id:04x}{vendor_id:04x}")


def _uuid_bytes(u: uuid.UUID, little: bool) -> bytes:
    return u.bytes_le if little else u.bytes


def _uuid_from(raw: bytes, little: bool) -> uuid.UUID:
    return uuid.UUID(bytes_le=raw) if little else uuid.UUID(bytes=raw)


@dataclass(frozen=True)
class RpcHeader:
    """The 80-byte connectionless DCE/RPC header."""

    ptype: int
    object: uuid.UUID
    interface: uuid.UUID
    activity: uuid.UUID
    seqnum: int
    opnum: int
    body_length: int
    little: bool = True
    flags1: int = 0x20  # idempotent
    flags2: int = 0
    server_boot: int = 0
    interface_version: int = 1
    fragnum: int = 0
    serial: int = 0

    def pack(self) -> bytes:
        o = "<" if self.little else ">"
        drep = bytes([0x10 if self.little else 0x00, 0, 0])
        return (struct.pack("BBBB", 4, self.ptype, self.flags1, self.flags2) + drep
                + bytes([self.serial >> 8 & 0xFF])
                + _uuid_bytes(self.object, self.little) + _uuid_bytes(self.interface, self.little)
                + _uuid_bytes(self.activity, self.little)
                + struct.pack(o + "IIIHHHHH", self.server_boot, self.interface_version,
                              self.seqnum, self.opnum, 0xFFFF, 0xFFFF, self.body_length,
                              self.fragnum)
                + bytes([0, self.serial & 0xFF]))

    @classmethod
    def unpack(cls, raw: bytes) -> RpcHeader:
        if len(raw) < HEADER_SIZE:
            raise FrameError(f"RPC datagram of {len(raw)} bytes is shorter than its 80-byte "
                             "header")
        if raw[0] != 4:
            raise FrameError(f"RPC version {raw[0]} is not 4 (connectionless)")
        little = bool(raw[4] & 0x10)
        o = "<" if little else ">"
        boot, iver, seq, op, _ih, _ah, blen, frag = struct.unpack_from(o + "IIIHHHHH", raw, 56)
        return cls(raw[1], _uuid_from(raw[8:24], little), _uuid_from(raw[24:40], little),
                   _uuid_from(raw[40:56], little), seq, op, blen, little, raw[2], raw[3], boot,
                   iver, frag, raw[7] << 8 | raw[79])


def request(object_: uuid.UUID, activity: uuid.UUID, seqnum: int, opnum: int, body: bytes,
            interface: uuid.UUID = IFACE_DEVICE, args_max: int = 16384) -> bytes:
    """A whole PNIO request datagram (little-endian header and NDR wrapper, as controllers
    send them): the header, then ArgsMaximum and the NDR counts, then ``body``."""
    ndr = Ndr(args_max, body, args_max).pack(True, response=False)
    return RpcHeader(REQUEST, object_, interface, activity, seqnum, opnum, len(ndr),
                     True).pack() + ndr


def response(head: RpcHeader, status: int, body: bytes) -> bytes:
    """The response datagram to the request ``head``: PNIOStatus, then ``body``."""
    ndr = Ndr(status, body, len(body)).pack(head.little, response=True)
    return RpcHeader(RESPONSE, head.object, head.interface, head.activity, head.seqnum,
                     head.opnum, len(ndr), head.little, flags1=0x0A,
                     interface_version=head.interface_version, serial=head.serial
                     ).pack() + ndr


@dataclass(frozen=True)
class Ndr:
    """The NDR wrapper of a PNIO request (ArgsMaximum) or response (PNIOStatus), with
    ArgsLength, MaximumCount, Offset and ActualCount, in the header's byte order."""

    first: int  # ArgsMaximum in a request, PNIOStatus (as a big-endian u32) in a response
    body: bytes
    maximum_count: int = 0

    def pack(self, little: bool, response: bool) -> bytes:
        o = "<" if little else ">"
        head = (struct.pack(">I", self.first) if response else struct.pack(o + "I", self.first))
        return head + struct.pack(o + "IIII", len(self.body), self.maximum_count or
                                  max(len(self.body), self.first if not response else 0),
                                  0, len(self.body)) + self.body

    @classmethod
    def unpack(cls, raw: bytes, little: bool, response: bool = False) -> Ndr:
        """``response``: the first field is PNIOStatus, always big-endian."""
        if len(raw) < NDR_SIZE:
            raise FrameError(f"NDR data of {len(raw)} bytes is shorter than its 20-byte header")
        o = "<" if little else ">"
        args_max, args_len, max_count, _off, actual = struct.unpack_from(o + "IIIII", raw, 0)
        if response:
            args_max, = struct.unpack_from(">I", raw, 0)
        if NDR_SIZE + actual > len(raw) or actual > args_len + 4096:
            raise FrameError(f"NDR ActualCount {actual} runs past the datagram's "
                             f"{len(raw) - NDR_SIZE} bytes")
        return cls(args_max, raw[NDR_SIZE:NDR_SIZE + actual], max_count)


def pnio_status(code: int = 0, decode: int = 0, code1: int = 0, code2: int = 0) -> int:
    """PNIOStatus as one u32: ErrorCode, ErrorDecode, ErrorCode1, ErrorCode2."""
    return code << 24 | decode << 16 | code1 << 8 | code2


def connect_error(code1: int, code2: int) -> int:
    """A PNIOStatus rejecting a Connect (ErrorCode 0xDB IODConnectRes, ErrorDecode 0x81 PNIO)."""
    return pnio_status(0xDB, 0x81, code1, code2)
