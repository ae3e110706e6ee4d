"""EtherNet/IP frames as dataclasses with ``pack()`` / ``unpack()``, nothing else: the
encapsulation, the common packet format and the class 1 I/O datagram (the CIP messages they
carry are in :mod:`.cip`).

Field names follow the ODVA specification: "The CIP Networks Library", Volume 2 (EtherNet/IP
adaptation: chapter 2 encapsulation, 2-6 common packet format, 3-2 I/O transport) and Volume 1
(CIP Common, edition 3.x). Every value is little-endian (CIP's byte order) except the socket
address items, which are in network order as the specification says (Vol 2, 2-6.3.2). A frame
that does not fit raises :class:`FrameError`, naming what is wrong; nothing here knows sockets,
clocks or the layout.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

ENCAP_HEADER = struct.Struct("<HHII8sI")
ENCAP_HEADER_SIZE = ENCAP_HEADER.size  # 24
PROTOCOL_VERSION = 1
TCP_PORT = 44818
UDP_IO_PORT = 2222


class FrameError(ValueError):
    """Bytes that are not the frame they should be; ``status`` is the protocol's answer code
    (an encapsulation status or a CIP general status, by who raises it)."""

    def __init__(self, message: str, status: int = 0x03) -> None:
        super().__init__(message)
        self.status = status


class Command(IntEnum):
    """Encapsulation commands (Vol 2, 2-3.2)."""

    NOP = 0x0000
    LIST_SERVICES = 0x0004
    LIST_IDENTITY = 0x0063
    LIST_INTERFACES = 0x0064
    REGISTER_SESSION = 0x0065
    UNREGISTER_SESSION = 0x0066
    SEND_RR_DATA = 0x006F
    SEND_UNIT_DATA = 0x0070


class EncapStatus(IntEnum):
    """Encapsulation status codes (Vol 2, 2-3.3)."""

    SUCCESS = 0x0000
    INVALID_COMMAND = 0x0001
    INSUFFICIENT_MEMORY = 0x0002
    INCORRECT_DATA = 0x0003
    INVALID_SESSION = 0x0064
    INVALID_LENGTH = 0x0065
    UNSUPPORTED_PROTOCOL = 0x0069


class ItemType(IntEnum):
    """Common packet format item type ids (Vol 2, 2-6.1)."""

    NULL_ADDRESS = 0x0000
    LIST_IDENTITY = 0x000C
    CONNECTED_ADDRESS = 0x00A1
    CONNECTED_DATA = 0x00B1
    UNCONNECTED_DATA = 0x00B2
    LIST_SERVICES = 0x0100
    SOCKADDR_O_T = 0x8000
    SOCKADDR_T_O = 0x8001
    SEQUENCED_ADDRESS = 0x8002


# ---------------------------------------------------------------------------- encapsulation


@dataclass(frozen=True)
class Encapsulation:
    """One encapsulation message (Vol 2, 2-3.1): the 24-byte header and its data."""

    command: int
    session_handle: int = 0
    status: int = 0
    sender_context: bytes = bytes(8)
    options: int = 0
    data: bytes = b""

    def pack(self) -> bytes:
        return ENCAP_HEADER.pack(self.command, len(self.data), self.session_handle,
                                 self.status, self.sender_context, self.options) + self.data

    @staticmethod
    def length_of(header: bytes) -> int:
        """The whole message's length from its first 24 bytes."""
        return ENCAP_HEADER_SIZE + int.from_bytes(header[2:4], "little")

    @classmethod
    def unpack(cls, raw: bytes) -> Encapsulation:
        if len(raw) < ENCAP_HEADER_SIZE:
            raise FrameError(f"encapsulation header: {len(raw)} bytes, need 24",
                             EncapStatus.INVALID_LENGTH)
        command, length, session, status, context, options = ENCAP_HEADER.unpack_from(raw)
        data = raw[ENCAP_HEADER_SIZE:]
        if len(data) != length:
            raise FrameError(f"encapsulation length field says {length} bytes of data, "
                             f"{len(data)} follow", EncapStatus.INVALID_LENGTH)
        return cls(command, session, status, context, options, bytes(data))

    def reply(self, data: bytes = b"", status: int = 0, session: int | None = None
              ) -> Encapsulation:
        """The answer to this message: same command and sender context (Vol 2, 2-3.1)."""
        return Encapsulation(self.command, self.session_handle if session is None else session,
                             status, self.sender_context, 0, data)


@dataclass(frozen=True)
class Item:
    """One common packet format item (Vol 2, 2-6): type id, then its data."""

    type_id: int
    data: bytes = b""

    def pack(self) -> bytes:
        return struct.pack("<HH", self.type_id, len(self.data)) + self.data


def pack_items(items: list[Item]) -> bytes:
    """A common packet format: item count, then the items (Vol 2, 2-6)."""
    return struct.pack("<H", len(items)) + b"".join(i.pack() for i in items)


def unpack_items(raw: bytes) -> list[Item]:
    if len(raw) < 2:
        raise FrameError("common packet format: no item count")
    (count,), at, items = struct.unpack_from("<H", raw), 2, []
    for n in range(count):
        if at + 4 > len(raw):
            raise FrameError(f"common packet format: item {n} of {count} is missing")
        type_id, length = struct.unpack_from("<HH", raw, at)
        at += 4
        if at + length > len(raw):
            raise FrameError(f"common packet format: item {n} (type 0x{type_id:04X}) says "
                             f"{length} bytes, {len(raw) - at} follow")
        items.append(Item(type_id, bytes(raw[at : at + length])))
        at += length
    if at != len(raw):
        raise FrameError(f"common packet format: {len(raw) - at} bytes after the last item")
    return items


@dataclass(frozen=True)
class SendData:
    """SendRRData / SendUnitData command data (Vol 2, 2-4.7, 2-4.8): interface handle (0 for
    CIP), timeout, and the common packet format."""

    items: list[Item]
    interface_handle: int = 0
    timeout: int = 0

    def pack(self) -> bytes:
        return struct.pack("<IH", self.interface_handle, self.timeout) + pack_items(self.items)

    @classmethod
    def unpack(cls, raw: bytes) -> SendData:
        if len(raw) < 6:
            raise FrameError(f"send data: {len(raw)} bytes, need at least 8")
        handle, timeout = struct.unpack_from("<IH", raw)
        return cls(unpack_items(raw[6:]), handle, timeout)


@dataclass(frozen=True)
class SocketAddress:
    """A socket address item's data (Vol 2, 2-6.3.2): big-endian sockaddr_in."""

    port: int
    address: int = 0  # IPv4 as an int; 0: the sender's own address

    def pack(self) -> bytes:
        return struct.pack(">hHI8s", 2, self.port, self.address, bytes(8))

    @classmethod
    def unpack(cls, raw: bytes) -> SocketAddress:
        if len(raw) != 16:
            raise FrameError(f"socket address item: {len(raw)} bytes, need 16")
        family, port, address, _zero = struct.unpack(">hHI8s", raw)
        if family != 2:
            raise FrameError(f"socket address item: sin_family {family}, need 2 (AF_INET)")
        return cls(port, address)


@dataclass(frozen=True)
class Identity:
    """The identity a ListIdentity reply carries (Vol 2, 2-4.3.2), also the Identity object's
    instance attributes 1-7 (Vol 1, 5-2)."""

    vendor_id: int
    device_type: int
    product_code: int
    revision: tuple[int, int]
    serial_number: int
    product_name: str
    status: int = 0
    state: int = 3  # operational

    def attributes_all(self) -> bytes:
        """Get_Attributes_All of the Identity instance: attributes 1 to 7 in order."""
        name = self.product_name.encode("ascii")
        return struct.pack("<HHHBBHIB", self.vendor_id, self.device_type, self.product_code,
                           *self.revision, self.status, self.serial_number, len(name)) + name

    def list_identity_item(self, address: SocketAddress) -> Item:
        name = self.product_name.encode("ascii")
        body = (struct.pack("<H", PROTOCOL_VERSION) + address.pack()
                + struct.pack("<HHHBBHIB", self.vendor_id, self.device_type, self.product_code,
                              *self.revision, self.status, self.serial_number, len(name))
                + name + bytes([self.state]))
        return Item(ItemType.LIST_IDENTITY, body)


def list_services_item() -> Item:
    """The one service a CIP device lists (Vol 2, 2-4.6.3): "Communications", with the
    capability flags for CIP over TCP (bit 5) and class 0/1 I/O over UDP (bit 8)."""
    return Item(ItemType.LIST_SERVICES,
                struct.pack("<HH16s", PROTOCOL_VERSION, 0x0120, b"Communications"))


# ---------------------------------------------------------------------------- class 1 I/O

RUN = 0x0000_0001  # the 32-bit run/idle header's run bit (Vol 1, 3-6.1)


@dataclass(frozen=True)
class IoFrame:
    """A class 0/1 I/O datagram on UDP 2222 (Vol 2, 3-2.1): a sequenced address item
    (connection id, encapsulation sequence number) and a connected data item (the 16-bit CIP
    sequence count, then the connection's data; O→T data starts with the run/idle header)."""

    connection_id: int
    encap_sequence: int
    sequence_count: int
    data: bytes

    def pack(self) -> bytes:
        return pack_items([
            Item(ItemType.SEQUENCED_ADDRESS,
                 struct.pack("<II", self.connection_id, self.encap_sequence)),
            Item(ItemType.CONNECTED_DATA, struct.pack("<H", self.sequence_count) + self.data),
        ])

    @classmethod
    def unpack(cls, raw: bytes) -> IoFrame:
        items = unpack_items(raw)
        if len(items) != 2 or items[0].type_id != ItemType.SEQUENCED_ADDRESS \
                or items[1].type_id != ItemType.CONNECTED_DATA:
            kinds = ", ".join(f"0x{i.type_id:04X}" for i in items)
            raise FrameError(f"I/O datagram: items {kinds}, need 0x8002 then 0x00B1")
        if len(items[0].data) != 8 or len(items[1].data) < 2:
            raise FrameError("I/O datagram: address item must be 8 bytes, data at least 2")
        conn_id, seq = struct.unpack("<II", items[0].data)
        (count,) = struct.unpack_from("<H", items[1].data)
        return cls(conn_id, seq, count, items[1].data[2:])


def run_idle(run: bool) -> bytes:
    return struct.pack("<I", RUN if run else 0)


def newer(count: int, last: int) -> bool:
    """Whether 16-bit sequence count ``count`` comes after ``last`` (Vol 1, 3-4.4.5: counts
    compare modulo 2**16)."""
    return 0 < (count - last) & 0xFFFF < 0x8000
