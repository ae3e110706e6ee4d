"""The identification records: I&M0 and RealIdentificationData as a Read answers them, and the
I&M1..I&M4 records (Identification & Maintenance, IEC 61158-6-10 "I&M1".."I&M4"; index
0xAFF1..0xAFF4 on the device access point), sans-I/O: what a Read answers and what a Write
may carry. Each record is its BlockHeader (BlockType 0x0021..0x0024, version 1.0) followed by
fixed-size fields, strings padded with blanks, I&M4's signature with zeros.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from . import blocks
from . import modules as mod

if TYPE_CHECKING:
    from .dcp import Identity


@dataclass(frozen=True)
class ImRecord:
    """One I&M record: its index, BlockType, the sizes of its fields and its padding byte."""

    number: int
    index: int
    block_type: int
    fields: tuple[tuple[str, int], ...]
    pad: bytes  # b" " for VisibleString fields, b"\0" for OctetString

    @property
    def size(self) -> int:
        """The data after the BlockHeader, in bytes."""
        return sum(n for _, n in self.fields)


RECORDS: Final = {r.index: r for r in (
    ImRecord(1, 0xAFF1, 0x0021, (("IM_Tag_Function", 32), ("IM_Tag_Location", 22)), b" "),
    ImRecord(2, 0xAFF2, 0x0022, (("IM_Date", 16),), b" "),
    ImRecord(3, 0xAFF3, 0x0023, (("IM_Descriptor", 54),), b" "),
    ImRecord(4, 0xAFF4, 0x0024, (("IM_Signature", 54),), b"\0"),
)}
# IM_Supported of I&M0: bit n says I&Mn is there
IM_SUPPORTED: Final = sum(1 << r.number for r in RECORDS.values())

# PNIORW ErrorCode1 of a refused Write (IEC 61158-6-10, "ErrorCode1", class Access)
WRITE_LENGTH_ERROR: Final = 0xB1
INVALID_PARAMETER: Final = 0xB8


def default(record: ImRecord) -> bytes:
    """A record nobody wrote yet: all padding."""
    return record.pad * record.size


def block(record: ImRecord, data: bytes) -> bytes:
    """The whole record a Read answers: BlockHeader and ``data``."""
    return struct.pack(">HHBB", record.block_type, record.size + 2, 1, 0) + data


def written(record: ImRecord, raw: bytes) -> tuple[bytes | None, int]:
    """The data a Write of ``raw`` (BlockHeader and fields) stores, or None and the
    ErrorCode1 that refuses it: a wrong length (WRITE_LENGTH_ERROR), another BlockType or
    BlockLength, or a string that is not printable ASCII (INVALID_PARAMETER)."""
    if len(raw) != 6 + record.size:
        return None, WRITE_LENGTH_ERROR
    btype, blen, major, _minor = struct.unpack_from(">HHBB", raw, 0)
    if btype != record.block_type or blen != record.size + 2 or major != 1:
        return None, INVALID_PARAMETER
    data = raw[6:]
    if record.pad == b" " and any(not 0x20 <= c <= 0x7E for c in data):
        return None, INVALID_PARAMETER
    return data, 0


def text(record: ImRecord, values: dict[str, str | bytes]) -> bytes:
    """A record's data from its fields' values (padded; too long is a ValueError)."""
    out = b""
    for name, n in record.fields:
        value = values.get(name, b"")
        raw = value.encode("ascii") if isinstance(value, str) else value
        if len(raw) > n:
            raise ValueError(f"I&M{record.number} {name} is {len(raw)} bytes, at most {n}")
        out += raw.ljust(n, record.pad)
    return out


def im0(ident: Identity) -> bytes:
    """I&M0 (index 0xAFF0 on the device access point): who made the device, which it is, and
    which I&M records it has."""
    major, minor, patch = ident.software
    body = (struct.pack(">H", ident.vendor_id)
            + ident.order_id.encode("ascii")[:20].ljust(20)
            + ident.serial.encode("ascii")[:16].ljust(16)
            + struct.pack(">H", 1) + b"V" + bytes([major, minor, patch])
            + struct.pack(">HHHBBH", 0, 0, 0x0005, 1, 1, IM_SUPPORTED))
    return blocks.block(blocks.BLOCK_IM0, body)


def real_identification() -> bytes:
    """RealIdentificationData (index 0xF000): the slots and submodules the device has."""
    slots: dict[int, list[mod.Submodule]] = {}
    for s in mod.SUBMODULES:
        slots.setdefault(s.slot, []).append(s)
    body = struct.pack(">H", len(slots))
    for slot, subs in slots.items():
        body += struct.pack(">HIH", slot, subs[0].module_ident, len(subs))
        for s in subs:
            body += struct.pack(">HI", s.subslot, s.submodule_ident)
    return blocks.block(blocks.BLOCK_REAL_IDENTIFICATION, body)
