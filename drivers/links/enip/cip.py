"""CIP messages as dataclasses with ``pack()`` / ``unpack()``: the EPATH, Message Router
requests and responses, Unconnected Send and the Connection Manager's Forward Open / Large
Forward Open / Forward Close, with the status codes answered.

Field names follow "The CIP Networks Library", Volume 1 (edition 3.x: chapter 2 messaging, 3-5
the Connection Manager, appendix B status codes, appendix C the EPATH). Little-endian
throughout; a message that does not fit raises :class:`~.codec.FrameError` whose ``status`` is
the CIP general status to answer.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from enum import IntEnum

from .codec import FrameError


class Service(IntEnum):
    """CIP service codes used here (Vol 1, appendix A; Connection Manager 3-5.5)."""

    GET_ATTRIBUTES_ALL = 0x01
    SET_ATTRIBUTES_ALL = 0x02
    GET_ATTRIBUTE_SINGLE = 0x0E
    SET_ATTRIBUTE_SINGLE = 0x10
    FORWARD_CLOSE = 0x4E
    UNCONNECTED_SEND = 0x52
    FORWARD_OPEN = 0x54
    LARGE_FORWARD_OPEN = 0x5B


class GeneralStatus(IntEnum):
    """CIP general status codes (Vol 1, appendix B) answered here."""

    SUCCESS = 0x00
    CONNECTION_FAILURE = 0x01
    RESOURCE_UNAVAILABLE = 0x02
    PATH_SEGMENT_ERROR = 0x04
    PATH_DESTINATION_UNKNOWN = 0x05
    SERVICE_NOT_SUPPORTED = 0x08
    INVALID_ATTRIBUTE_VALUE = 0x09
    OBJECT_STATE_CONFLICT = 0x0C
    ATTRIBUTE_NOT_SETTABLE = 0x0E
    NOT_ENOUGH_DATA = 0x13
    ATTRIBUTE_NOT_SUPPORTED = 0x14
    TOO_MUCH_DATA = 0x15
    OBJECT_DOES_NOT_EXIST = 0x16
    INVALID_PARAMETER = 0x20


class ExtendedStatus(IntEnum):
    """Connection Manager extended status codes (Vol 1, table 3-5.33) answered here."""

    DUPLICATE_FORWARD_OPEN = 0x0100
    TRANSPORT_NOT_SUPPORTED = 0x0103
    OWNERSHIP_CONFLICT = 0x0106
    CONNECTION_NOT_FOUND = 0x0107
    INVALID_CONNECTION_TYPE = 0x0108
    RPI_NOT_SUPPORTED = 0x0111
    OUT_OF_CONNECTIONS = 0x0113
    VENDOR_OR_PRODUCT_MISMATCH = 0x0114
    DEVICE_TYPE_MISMATCH = 0x0115
    REVISION_MISMATCH = 0x0116
    INVALID_APPLICATION_PATH = 0x0117
    INVALID_CONFIGURATION_SIZE = 0x0126
    INVALID_O_T_SIZE = 0x0127
    INVALID_T_O_SIZE = 0x0128
    INVALID_SEGMENT = 0x0315


# ---------------------------------------------------------------------------- EPATH


@dataclass(frozen=True)
class Path:
    """A padded EPATH (Vol 1, appendix C), the segments this adapter understands: port
    (ignored: we are the end of the route), logical class / instance / connection point /
    attribute (8 and 16 bit), the electronic key (format 4) and a simple data segment."""

    class_id: int | None = None
    instance: int | None = None
    attribute: int | None = None
    points: tuple[int, ...] = ()  # connection points, in order
    key: tuple[int, int, int, int, int] | None = None  # vendor, type, product, major, minor
    compatibility: bool = False
    data: bytes | None = None
    ports: tuple[tuple[int, bytes], ...] = ()

    @classmethod
    def unpack(cls, raw: bytes) -> Path:
        found: dict[str, object] = {}
        points: list[int] = []
        ports: list[tuple[int, bytes]] = []
        at = 0
        while at < len(raw):
            seg = raw[at]
            kind = seg >> 5
            if kind == 0:  # port segment (C-1.4.2)
                port, at = seg & 0x0F, at + 1
                if port == 0x0F:
                    if at + 2 > len(raw):
                        raise FrameError("EPATH: a port segment is cut short", 0x04)
                    port, at = int.from_bytes(raw[at : at + 2], "little"), at + 2
                if seg & 0x10:
                    if at >= len(raw):
                        raise FrameError("EPATH: a port segment is cut short", 0x04)
                    size = raw[at]
                    link, at = bytes(raw[at + 1 : at + 1 + size]), at + 1 + size + (size & 1)
                else:
                    link, at = bytes(raw[at : at + 1]), at + 1
                ports.append((port, link))
            elif kind == 1:  # logical segment (C-1.4.3)
                ltype, fmt = (seg >> 2) & 0x07, seg & 0x03
                if ltype == 5 and fmt == 0:  # special: the electronic key
                    if at + 10 > len(raw) or raw[at + 1] != 4:
                        raise FrameError("EPATH: electronic key is not format 4", 0x04)
                    vendor, dtype, product, major, minor = struct.unpack_from("<HHHBB", raw,
                                                                              at + 2)
                    found["key"] = (vendor, dtype, product, major & 0x7F, minor)
                    found["compatibility"] = bool(major & 0x80)
                    at += 10
                    continue
                if fmt == 0:
                    size, pad = 1, 0
                elif fmt == 1:
                    size, pad = 2, 1
                elif fmt == 2:
                    size, pad = 4, 1
                else:
                    raise FrameError(f"EPATH: logical format {fmt} is reserved", 0x04)
                if at + 1 + pad + size > len(raw):
                    raise FrameError("EPATH: a logical segment is cut short", 0x04)
                value = int.from_bytes(raw[at + 1 + pad : at + 1 + pad + size], "little")
                at += 1 + pad + size
                if ltype == 0:
                    found["class_id"] = value
                elif ltype == 1:
                    found["instance"] = value
                elif ltype == 3:
                    points.append(value)
                elif ltype == 4:
                    found["attribute"] = value
                else:
                    raise FrameError(f"EPATH: logical type {ltype} is not supported", 0x04)
            elif seg == 0x80:  # simple data segment (C-1.4.5)
                if at + 2 > len(raw):
                    raise FrameError("EPATH: a data segment is cut short", 0x04)
                words = raw[at + 1]
                found["data"] = bytes(raw[at + 2 : at + 2 + 2 * words])
                if len(found["data"]) != 2 * words:  # type: ignore[arg-type]
                    raise FrameError("EPATH: a data segment is cut short", 0x04)
                at += 2 + 2 * words
            else:
                raise FrameError(f"EPATH: segment 0x{seg:02X} at byte {at} is not supported",
                                 0x04)
        return cls(points=tuple(points), ports=tuple(ports), **found)  # type: ignore[arg-type]

    def pack(self) -> bytes:
        out = b""
        for port, link in self.ports:
            out += (bytes([port]) + link if len(link) == 1
                    else bytes([0x10 | port, len(link)]) + link + bytes(len(link) & 1))
        if self.key is not None:
            vendor, dtype, product, major, minor = self.key
            out += struct.pack("<BBHHHBB", 0x34, 4, vendor, dtype, product,
                               major | (0x80 if self.compatibility else 0), minor)
        for ltype, value in (
            (0, self.class_id), (1, self.instance),
            *((3, p) for p in self.points), (4, self.attribute),
        ):
            if value is None:
                continue
            base = 0x20 | (ltype << 2)
            out += (bytes([base, value]) if value < 0x100
                    else struct.pack("<BBH", base | 1, 0, value))
        if self.data is not None:
            out += bytes([0x80, len(self.data) // 2]) + self.data
        return out


# ---------------------------------------------------------------------------- message router


@dataclass(frozen=True)
class Request:
    """A Message Router request (Vol 1, 2-4.1): service, request path (size in words), data."""

    service: int
    path: Path
    data: bytes = b""

    def pack(self) -> bytes:
        raw = self.path.pack()
        return bytes([self.service, len(raw) // 2]) + raw + self.data

    @classmethod
    def unpack(cls, raw: bytes) -> Request:
        if len(raw) < 2:
            raise FrameError(f"message router request: {len(raw)} bytes, need 2",
                             GeneralStatus.NOT_ENOUGH_DATA)
        service, words = raw[0], raw[1]
        if 2 + 2 * words > len(raw):
            raise FrameError(f"message router request: path of {words} words, "
                             f"{(len(raw) - 2) // 2} follow", GeneralStatus.PATH_SEGMENT_ERROR)
        return cls(service, Path.unpack(raw[2 : 2 + 2 * words]), bytes(raw[2 + 2 * words :]))


@dataclass(frozen=True)
class Response:
    """A Message Router response (Vol 1, 2-4.2): reply service (service | 0x80), general
    status, additional status words, data."""

    service: int
    status: int = 0
    extended: tuple[int, ...] = ()
    data: bytes = b""

    def pack(self) -> bytes:
        return (bytes([self.service | 0x80, 0, self.status, len(self.extended)])
                + b"".join(struct.pack("<H", w) for w in self.extended) + self.data)

    @classmethod
    def unpack(cls, raw: bytes) -> Response:
        if len(raw) < 4 or not raw[0] & 0x80:
            raise FrameError(f"message router response: {raw[:4].hex()} is no reply")
        words = raw[3]
        extended = struct.unpack_from(f"<{words}H", raw, 4)
        return cls(raw[0] & 0x7F, raw[2], tuple(extended), bytes(raw[4 + 2 * words :]))


@dataclass(frozen=True)
class UnconnectedSend:
    """Unconnected Send's request data (Vol 1, 3-5.5.4): priority/tick, timeout ticks, the
    embedded request, its pad byte, and the route path."""

    request: bytes
    route: Path = field(default_factory=Path)
    priority_time_tick: int = 0x0A
    timeout_ticks: int = 0xF0

    def pack(self) -> bytes:
        route = self.route.pack()
        pad = b"\x00" if len(self.request) & 1 else b""
        return (struct.pack("<BBH", self.priority_time_tick, self.timeout_ticks,
                            len(self.request)) + self.request + pad
                + bytes([len(route) // 2, 0]) + route)

    @classmethod
    def unpack(cls, raw: bytes) -> UnconnectedSend:
        if len(raw) < 4:
            raise FrameError("unconnected send: shorter than its 4-byte header",
                             GeneralStatus.NOT_ENOUGH_DATA)
        tick, ticks, size = struct.unpack_from("<BBH", raw)
        end = 4 + size + (size & 1)
        if end + 2 > len(raw):
            raise FrameError(f"unconnected send: message of {size} bytes and a route path "
                             f"do not fit in {len(raw) - 4}", GeneralStatus.NOT_ENOUGH_DATA)
        words = raw[end]
        route = raw[end + 2 : end + 2 + 2 * words]
        if len(route) != 2 * words:
            raise FrameError("unconnected send: the route path is cut short",
                             GeneralStatus.PATH_SEGMENT_ERROR)
        return cls(bytes(raw[4 : 4 + size]), Path.unpack(route), tick, ticks)


# ---------------------------------------------------------------------------- connection manager

TIMEOUT_MULTIPLIERS = (4, 8, 16, 32, 64, 128, 256, 512)


@dataclass(frozen=True)
class NetworkParameters:
    """Network connection parameters (Vol 1, 3-5.5.1.1): the 16-bit form of Forward Open and
    the 32-bit form of Large Forward Open, decoded."""

    size: int  # bytes, including the sequence count and run/idle header where present
    variable: bool = False
    priority: int = 2  # scheduled
    connection_type: int = 2  # 0 null, 1 multicast, 2 point to point
    redundant_owner: bool = False

    def pack(self, large: bool) -> bytes:
        if large:
            return struct.pack("<I", self.size | self.variable << 25 | self.priority << 26
                               | self.connection_type << 29 | self.redundant_owner << 31)
        return struct.pack("<H", self.size | self.variable << 9 | self.priority << 10
                           | self.connection_type << 13 | self.redundant_owner << 15)

    @classmethod
    def decode(cls, word: int, large: bool) -> NetworkParameters:
        if large:
            return cls(word & 0xFFFF, bool(word >> 25 & 1), word >> 26 & 3, word >> 29 & 3,
                       bool(word >> 31 & 1))
        return cls(word & 0x1FF, bool(word >> 9 & 1), word >> 10 & 3, word >> 13 & 3,
                   bool(word >> 15 & 1))


@dataclass(frozen=True)
class ForwardOpen:
    """Forward Open (0x54) and Large Forward Open (0x5B) request data (Vol 1, 3-5.5.2)."""

    o_t_connection_id: int
    t_o_connection_id: int
    connection_serial: int
    originator_vendor_id: int
    originator_serial: int
    timeout_multiplier: int
    o_t_rpi_us: int
    o_t_parameters: NetworkParameters
    t_o_rpi_us: int
    t_o_parameters: NetworkParameters
    transport_type_trigger: int
    path: Path
    large: bool = False
    priority_time_tick: int = 0x0A
    timeout_ticks: int = 0xF0

    @property
    def transport_class(self) -> int:
        return self.transport_type_trigger & 0x0F

    @property
    def triple(self) -> tuple[int, int, int]:
        """What names a connection (Vol 1, 3-5.5.2.2): serial, vendor, originator serial."""
        return (self.connection_serial, self.originator_vendor_id, self.originator_serial)

    def timeout_s(self) -> float:
        """The consumer's inactivity timeout: O→T RPI × multiplier (Vol 1, 3-4.4.9)."""
        return self.o_t_rpi_us * TIMEOUT_MULTIPLIERS[self.timeout_multiplier & 7] / 1e6

    def pack(self) -> bytes:
        path = self.path.pack()
        return (struct.pack("<BBIIHHIB3sI", self.priority_time_tick, self.timeout_ticks,
                            self.o_t_connection_id, self.t_o_connection_id,
                            self.connection_serial, self.originator_vendor_id,
                            self.originator_serial, self.timeout_multiplier, bytes(3),
                            self.o_t_rpi_us)
                + self.o_t_parameters.pack(self.large) + struct.pack("<I", self.t_o_rpi_us)
                + self.t_o_parameters.pack(self.large)
                + bytes([self.transport_type_trigger, len(path) // 2]) + path)

    @classmethod
    def unpack(cls, raw: bytes, large: bool) -> ForwardOpen:
        fmt = "<BBIIHHIB3sI" + ("I" if large else "H") + "I" + ("I" if large else "H") + "BB"
        head = struct.calcsize(fmt)
        name = "Large Forward Open" if large else "Forward Open"
        if len(raw) < head:
            raise FrameError(f"{name}: {len(raw)} bytes, need at least {head}",
                             GeneralStatus.NOT_ENOUGH_DATA)
        (tick, ticks, ot_id, to_id, serial, vendor, oserial, mult, _r, ot_rpi, ot_par, to_rpi,
         to_par, trigger, words) = struct.unpack_from(fmt, raw)
        path = raw[head : head + 2 * words]
        if len(path) != 2 * words:
            raise FrameError(f"{name}: connection path of {words} words, "
                             f"{len(raw[head:]) // 2} follow", GeneralStatus.NOT_ENOUGH_DATA)
        if len(raw) > head + 2 * words:
            raise FrameError(f"{name}: {len(raw) - head - 2 * words} bytes after the "
                             "connection path", GeneralStatus.TOO_MUCH_DATA)
        return cls(ot_id, to_id, serial, vendor, oserial, mult, ot_rpi,
                   NetworkParameters.decode(ot_par, large), to_rpi,
                   NetworkParameters.decode(to_par, large), trigger, Path.unpack(path), large,
                   tick, ticks)


@dataclass(frozen=True)
class ForwardOpenReply:
    """A successful Forward Open's reply data (Vol 1, 3-5.5.2.3)."""

    o_t_connection_id: int
    t_o_connection_id: int
    connection_serial: int
    originator_vendor_id: int
    originator_serial: int
    o_t_api_us: int
    t_o_api_us: int
    application_reply: bytes = b""

    def pack(self) -> bytes:
        return struct.pack("<IIHHIIIBB", self.o_t_connection_id, self.t_o_connection_id,
                           self.connection_serial, self.originator_vendor_id,
                           self.originator_serial, self.o_t_api_us, self.t_o_api_us,
                           len(self.application_reply) // 2, 0) + self.application_reply

    @classmethod
    def unpack(cls, raw: bytes) -> ForwardOpenReply:
        if len(raw) < 26:
            raise FrameError(f"Forward Open reply: {len(raw)} bytes, need 26")
        o_t, t_o, serial, vendor, oserial, o_api, t_api, words, _r = struct.unpack_from(
            "<IIHHIIIBB", raw)
        return cls(o_t, t_o, serial, vendor, oserial, o_api, t_api,
                   bytes(raw[26 : 26 + 2 * words]))


@dataclass(frozen=True)
class ForwardClose:
    """Forward Close request data (Vol 1, 3-5.5.3)."""

    connection_serial: int
    originator_vendor_id: int
    originator_serial: int
    path: Path = field(default_factory=Path)
    priority_time_tick: int = 0x0A
    timeout_ticks: int = 0xF0

    @property
    def triple(self) -> tuple[int, int, int]:
        return (self.connection_serial, self.originator_vendor_id, self.originator_serial)

    def pack(self) -> bytes:
        path = self.path.pack()
        return struct.pack("<BBHHIBB", self.priority_time_tick, self.timeout_ticks,
                           self.connection_serial, self.originator_vendor_id,
                           self.originator_serial, len(path) // 2, 0) + path

    @classmethod
    def unpack(cls, raw: bytes) -> ForwardClose:
        if len(raw) < 12:
            raise FrameError(f"Forward Close: {len(raw)} bytes, need at least 12",
                             GeneralStatus.NOT_ENOUGH_DATA)
        tick, ticks, serial, vendor, oserial, words, _r = struct.unpack_from("<BBHHIBB", raw)
        path = raw[12 : 12 + 2 * words]
        if len(path) != 2 * words:
            raise FrameError("Forward Close: the connection path is cut short",
                             GeneralStatus.NOT_ENOUGH_DATA)
        return cls(serial, vendor, oserial, Path.unpack(path), tick, ticks)


def forward_close_reply(close: ForwardClose) -> bytes:
    """A successful Forward Close's reply data (Vol 1, 3-5.5.3.2)."""
    return struct.pack("<HHIBB", *close.triple, 0, 0)
