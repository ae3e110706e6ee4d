"""PROFINET frames on Ethertype 0x8892, sans-I/O: Ethernet II (with or without an 802.1Q tag),
the cyclic RT_CLASS_1 frame and DCP (IEC 61158-6-10, "DCP" and "RT"), as dataclasses with
``pack()`` / ``unpack()``. Every value is big-endian (network order), as the spec fixes it.

A frame that does not fit raises :class:`FrameError` naming what is wrong; the device counts it
and drops it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import Final

ETHERTYPE_PN: Final = 0x8892
ETHERTYPE_VLAN: Final = 0x8100
ETHERTYPE_LLDP: Final = 0x88CC
DCP_MULTICAST: Final = bytes.fromhex("010ecf000000")
LLDP_MULTICAST: Final = bytes.fromhex("0180c200000e")
MIN_FRAME: Final = 60  # an Ethernet frame without its FCS

# FrameID ranges (IEC 61158-6-10, "FrameID")
FRAME_ID_RTC1_MIN: Final = 0xC000
FRAME_ID_RTC1_MAX: Final = 0xF7FF
FRAME_ID_ALARM_HIGH: Final = 0xFC01
FRAME_ID_ALARM_LOW: Final = 0xFE01
FRAME_ID_DCP_HELLO: Final = 0xFEFC
FRAME_ID_DCP_GET_SET: Final = 0xFEFD
FRAME_ID_DCP_IDENTIFY_REQ: Final = 0xFEFE
FRAME_ID_DCP_IDENTIFY_RES: Final = 0xFEFF

# DataStatus bits (IEC 61158-6-10, "DataStatus")
DATA_STATUS_PRIMARY: Final = 0x01
DATA_STATUS_VALID: Final = 0x04
DATA_STATUS_RUN: Final = 0x10
DATA_STATUS_STATION_OK: Final = 0x20
DATA_STATUS_GOOD: Final = DATA_STATUS_PRIMARY | DATA_STATUS_VALID | DATA_STATUS_RUN | \
    DATA_STATUS_STATION_OK
IOXS_GOOD: Final = 0x80
IOXS_BAD: Final = 0x00


class FrameError(ValueError):
    """Bytes that are not the frame they claim to be."""


def mac_text(mac: bytes) -> str:
    return ":".join(f"{b:02x}" for b in mac)


@dataclass(frozen=True)
class Ethernet:
    """Ethernet II header, optionally 802.1Q tagged (RT frames carry priority 6, VID 0)."""

    dst: bytes
    src: bytes
    ethertype: int
    payload: bytes
    vlan_tci: int | None = None

    def pack(self) -> bytes:
        tag = b"" if self.vlan_tci is None else struct.pack(">HH", ETHERTYPE_VLAN, self.vlan_tci)
        raw = self.dst + self.src + tag + struct.pack(">H", self.ethertype) + self.payload
        return raw.ljust(MIN_FRAME, b"\0")

    @classmethod
    def unpack(cls, raw: bytes) -> Ethernet:
        if len(raw) < 14:
            raise FrameError(f"Ethernet frame of {len(raw)} bytes is shorter than its header")
        dst, src = raw[0:6], raw[6:12]
        (etype,) = struct.unpack_from(">H", raw, 12)
        tci, at = None, 14
        if etype == ETHERTYPE_VLAN:
            if len(raw) < 18:
                raise FrameError("802.1Q tag cut short")
            tci, etype = struct.unpack_from(">HH", raw, 14)
            at = 18
        return cls(dst, src, etype, raw[at:], tci)


@dataclass(frozen=True)
class RtFrame:
    """A cyclic RT_CLASS_1 frame after the Ethertype: FrameID, C_SDU (process data with IOPS
    and IOCS at the offsets the IOCR gives), APDU status (CycleCounter in 31.25 µs units,
    DataStatus, TransferStatus)."""

    frame_id: int
    c_sdu: bytes
    cycle_counter: int
    data_status: int
    transfer_status: int = 0

    def pack(self) -> bytes:
        return (struct.pack(">H", self.frame_id) + self.c_sdu
                + struct.pack(">HBB", self.cycle_counter & 0xFFFF, self.data_status,
                              self.transfer_status))

    @classmethod
    def unpack(cls, payload: bytes, data_length: int) -> RtFrame:
        """``payload`` after the Ethertype; ``data_length`` is the IOCR's C_SDU length (the
        Ethernet padding after the APDU status is ignored)."""
        if len(payload) < 2 + data_length + 4:
            raise FrameError(f"RT frame of {len(payload)} bytes is shorter than its IOCR's "
                             f"{data_length} bytes of C_SDU and 4 of status")
        (frame_id,) = struct.unpack_from(">H", payload, 0)
        cc, ds, ts = struct.unpack_from(">HBB", payload, 2 + data_length)
        return cls(frame_id, payload[2:2 + data_length], cc, ds, ts)


# --------------------------------------------------------------------------- DCP

class Service:
    """DCP ServiceID and ServiceType (IEC 61158-6-10, "DCP-PDU")."""

    GET: Final = 3
    SET: Final = 4
    IDENTIFY: Final = 5
    HELLO: Final = 6
    REQUEST: Final = 0
    SUCCESS: Final = 1
    UNSUPPORTED: Final = 5


class Opt:
    """DCP options and suboptions as (option, suboption)."""

    IP_MAC: Final = (1, 1)
    IP_PARAMETER: Final = (1, 2)
    VENDOR: Final = (2, 1)  # DeviceVendorValue (TypeOfStation)
    NAME_OF_STATION: Final = (2, 2)
    DEVICE_ID: Final = (2, 3)
    DEVICE_ROLE: Final = (2, 4)
    DEVICE_OPTIONS: Final = (2, 5)
    ALIAS_NAME: Final = (2, 6)
    DEVICE_INSTANCE: Final = (2, 7)
    CONTROL_START: Final = (5, 1)
    CONTROL_STOP: Final = (5, 2)
    CONTROL_SIGNAL: Final = (5, 3)
    CONTROL_RESPONSE: Final = (5, 4)
    CONTROL_FACTORY_RESET: Final = (5, 5)
    CONTROL_RESET_TO_FACTORY: Final = (5, 6)
    DEVICE_INITIATIVE: Final = (6, 1)
    ALL: Final = (0xFF, 0xFF)


# BlockError of a Control/Response block (IEC 61158-6-10, "DCP BlockError")
BLOCK_OK: Final = 0x00
BLOCK_OPTION_UNSUPPORTED: Final = 0x01
BLOCK_SUBOPTION_UNSUPPORTED: Final = 0x02
BLOCK_SUBOPTION_NOT_SET: Final = 0x03  # the value is not acceptable (e.g. a bad IP suite)
BLOCK_RESOURCE_ERROR: Final = 0x04
BLOCK_SET_NOT_POSSIBLE: Final = 0x05  # by local reasons (e.g. the device's own setting)
BLOCK_IN_OPERATION: Final = 0x06  # in operation: Set not possible (an AR is open)


@dataclass(frozen=True)
class DcpBlock:
    """One DCP block: Option, Suboption, DCPBlockLength, then the block's data (for a response
    that starts with BlockInfo, for a Set request with BlockQualifier). Blocks are padded to an
    even length on the wire; the padding is not part of DCPBlockLength."""

    option: int
    suboption: int
    data: bytes

    @property
    def key(self) -> tuple[int, int]:
        return self.option, self.suboption

    def pack(self) -> bytes:
        raw = struct.pack(">BBH", self.option, self.suboption, len(self.data)) + self.data
        return raw + b"\0" * (len(raw) % 2)


@dataclass(frozen=True)
class Dcp:
    """DCP-PDU after the FrameID: ServiceID, ServiceType, Xid, ResponseDelay (reserved in a
    response), DCPDataLength, blocks."""

    frame_id: int
    service_id: int
    service_type: int
    xid: int
    response_delay: int
    blocks: tuple[DcpBlock, ...] = field(default_factory=tuple)

    def pack(self) -> bytes:
        body = b"".join(b.pack() for b in self.blocks)
        return struct.pack(">HBBIHH", self.frame_id, self.service_id, self.service_type,
                           self.xid, self.response_delay, len(body)) + body

    @classmethod
    def unpack(cls, payload: bytes) -> Dcp:
        if len(payload) < 12:
            raise FrameError(f"DCP PDU of {len(payload)} bytes is shorter than its 12-byte header")
        frame_id, sid, stype, xid, delay, length = struct.unpack_from(">HBBIHH", payload, 0)
        if 12 + length > len(payload):
            raise FrameError(f"DCPDataLength {length} runs past the frame's "
                             f"{len(payload) - 12} bytes")
        blocks, at, end = [], 12, 12 + length
        while at < end:
            if at + 4 > end:
                raise FrameError(f"DCP block header cut short at byte {at}")
            opt, sub, blen = struct.unpack_from(">BBH", payload, at)
            if at + 4 + blen > end:
                raise FrameError(f"DCP block ({opt}, {sub}) of {blen} bytes runs past "
                                 f"DCPDataLength")
            blocks.append(DcpBlock(opt, sub, payload[at + 4:at + 4 + blen]))
            at += 4 + blen + (blen % 2)
        return cls(frame_id, sid, stype, xid, delay, tuple(blocks))


# --------------------------------------------------------------------------- LLDP

def lldp_frame(src: bytes, station_name: str, port_id: str, ttl_s: int = 20) -> bytes:
    """An LLDP frame (IEEE 802.1AB) as a PROFINET device sends it: chassis id = NameOfStation
    (subtype 7, locally assigned), port id (subtype 7), TTL, the MAC (IEEE 802.3 TLV is not
    needed for conformance class A), end."""

    def tlv(kind: int, value: bytes) -> bytes:
        return struct.pack(">H", (kind << 9) | len(value)) + value

    body = (tlv(1, b"\x07" + station_name.encode("ascii"))
            + tlv(2, b"\x07" + port_id.encode("ascii"))
            + tlv(3, struct.pack(">H", ttl_s))
            + tlv(4, b"mvpose " + mac_text(src).encode("ascii"))  # port description
            + tlv(0, b""))
    return Ethernet(LLDP_MULTICAST, src, ETHERTYPE_LLDP, body).pack()
