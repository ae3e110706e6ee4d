"""The EtherNet/IP adapter as a sans-I/O protocol core: bytes in, replies and events out.

The caller owns the sockets and the clock (h11's shape, STYLE.md): it feeds each TCP
connection's bytes to its :class:`~.session.TcpSession` (``receive_data``), each UDP datagram to
:meth:`Adapter.receive_io` or :meth:`Adapter.receive_udp_encapsulation`, calls
:meth:`Adapter.produce` and :meth:`Adapter.tick` on its timer, and drains
:meth:`Adapter.events` (:class:`OutputImage`, :class:`ConnectionOpened`,
:class:`ConnectionClosed`, :class:`Refused`).

The Connection Manager (Vol 1, 3-5) lives here: Forward Open / Large Forward Open / Forward
Close for class 1 I/O on the assemblies and class 3 explicit connections to the Message Router,
the connection table with its documented limit, the inactivity timeout (O→T RPI × multiplier)
and the producer's sequence counts (Vol 2, 3-2.1).
"""

from __future__ import annotations

import itertools
import struct
from dataclasses import dataclass

from .admission import Limits, refusal
from .cip import (
    ExtendedStatus,
    ForwardClose,
    ForwardOpen,
    ForwardOpenReply,
    GeneralStatus,
    Request,
    Response,
    Service,
    UnconnectedSend,
    forward_close_reply,
)
from .codec import (
    TCP_PORT,
    UDP_IO_PORT,
    Command,
    Encapsulation,
    FrameError,
    Identity,
    IoFrame,
    Item,
    ItemType,
    SocketAddress,
    list_services_item,
    newer,
    pack_items,
)
from .objects import CONNECTION_MANAGER, Assemblies, ObjectModel
from .session import TcpSession

# until a connection's first packet arrives its watchdog runs at least this long (CIP's initial
# inactivity timeout of 10 s), so a scanner slow to start producing is not dropped at once
INITIAL_TIMEOUT_S = 10.0


# ---------------------------------------------------------------------------- events


@dataclass(frozen=True)
class OutputImage:
    """The PLC's output image (the layout's OUTPUT block) as the adapter now holds it: a new
    class 1 image in run mode, zeros when the scanner went idle, or an explicit Set."""

    data: bytes
    peer: str
    how: str  # "io", "idle", "set"


@dataclass(frozen=True)
class ConnectionOpened:
    peer: str
    transport_class: int
    connection_id: int  # ours (O→T)
    rpi_ms: float


@dataclass(frozen=True)
class ConnectionClosed:
    peer: str
    transport_class: int
    connection_id: int
    why: str  # "forward close", "timed out", "session closed"


@dataclass(frozen=True)
class Refused:
    """Bad input answered with the protocol's status; nothing reached the handshake."""

    peer: str
    what: str
    status: str  # e.g. "encapsulation status 0x0064", "CIP 0x01/0x0127"


Event = OutputImage | ConnectionOpened | ConnectionClosed | Refused


# ---------------------------------------------------------------------------- connections


@dataclass
class Connection:
    """One open connection of the table."""

    peer: str
    request: ForwardOpen
    o_t_id: int  # ours: what the originator's packets carry
    t_o_id: int  # what our packets carry
    timeout_s: float
    last_rx: float
    session: TcpSession | None = None  # class 3: the session it was opened through
    destination: tuple[str, int] | None = None  # class 1: where T→O datagrams go
    api_s: float = 0.0
    next_tx: float = 0.0
    encap_sequence: int = 0
    sequence_count: int = 0
    last_count: int | None = None
    running: bool = False
    last_image: bytes | None = None  # what the last T→O datagram carried
    heard: bool = False  # a packet of the originator's has arrived since the Forward Open

    @property
    def change_of_state(self) -> bool:
        """The target produces on a change of its data too, RPI being the background rate
        (the production trigger of the transport type/trigger byte, Vol 1, 3-4.4.3)."""
        return (self.request.transport_type_trigger >> 4) & 7 == 1

    @property
    def transport_class(self) -> int:
        return self.request.transport_class


class Adapter:
    """One EtherNet/IP adapter: the connection table and the CIP objects."""

    def __init__(self, identity: Identity, assemblies: Assemblies | None = None,
                 limits: Limits | None = None, host: str = "127.0.0.1",
                 udp_port: int = UDP_IO_PORT, tcp_port: int = TCP_PORT) -> None:
        self.identity = identity
        self.assemblies = assemblies or Assemblies()
        self.limits = limits or Limits()
        self.host = host
        self.udp_port = udp_port
        self.tcp_port = tcp_port  # what ListIdentity says the encapsulation port is
        self.inputs = bytes(self.assemblies.input_size)
        self.outputs = bytes(self.assemblies.output_size)
        self.connections: dict[int, Connection] = {}  # by our O→T id
        self.sessions: dict[int, TcpSession] = {}
        self._events: list[Event] = []
        self._unknown: set[tuple[str, int]] = set()  # (peer, connection id) reported dropped
        self._ids = itertools.count(0x4D56_0001)  # "MV"...
        self._handles = itertools.count(1)
        self.objects = ObjectModel(identity, self.assemblies, host, lambda: self.inputs,
                                   lambda: self.outputs, self.owned)

    # --------------------------------------------------------------------- state

    def events(self) -> list[Event]:
        """Every event since the last call, oldest first."""
        out, self._events = self._events, []
        return out

    def owned(self) -> bool:
        """A class 1 exclusive owner holds the output assembly."""
        return any(c.transport_class == 1 for c in self.connections.values())

    def io_connections(self) -> list[Connection]:
        return [c for c in self.connections.values() if c.transport_class == 1]

    def session(self, peer: str) -> TcpSession:
        """A new TCP connection from ``peer``."""
        return TcpSession(self, peer)

    def refuse(self, peer: str, what: str, status: str) -> None:
        self._events.append(Refused(peer, what, status))

    # --------------------------------------------------------------------- UDP

    def receive_udp_encapsulation(self, datagram: bytes, peer: str) -> bytes | None:
        """ListIdentity (and ListServices) on UDP 44818 (Vol 2, 2-4.2): the reply, or None
        when the datagram is not one (nothing is answered on UDP for anything else)."""
        try:
            msg = Encapsulation.unpack(datagram)
        except FrameError as err:
            self.refuse(peer, f"UDP encapsulation: {err}", f"dropped ({err.status:#06x})")
            return None
        if msg.command == Command.LIST_IDENTITY:
            return msg.reply(self.list_identity()).pack()
        if msg.command == Command.LIST_SERVICES:
            return msg.reply(pack_items([list_services_item()])).pack()
        self.refuse(peer, f"UDP encapsulation command 0x{msg.command:04X}", "dropped")
        return None

    def list_identity(self) -> bytes:
        host = self.host if self.host not in ("", "0.0.0.0") else "0.0.0.0"
        address = int.from_bytes(bytes(int(p) for p in host.split(".")), "big") \
            if host.count(".") == 3 else 0
        return pack_items([self.identity.list_identity_item(SocketAddress(self.tcp_port, address))])

    def receive_io(self, datagram: bytes, peer: str, now: float) -> None:
        """A class 1 datagram from ``peer`` (Vol 2, 3-2.1). Unknown connections and wrong
        sizes are dropped (I/O has no answer) and reported as :class:`Refused`."""
        try:
            frame = IoFrame.unpack(datagram)
        except FrameError as err:
            self.refuse(peer, f"I/O datagram: {err}", "dropped")
            return
        conn = self.connections.get(frame.connection_id)
        if conn is None or conn.transport_class != 1 or conn.peer != peer:
            # a scanner sends on until it notices its connection gone: say so once per id
            if (peer, frame.connection_id) not in self._unknown:
                if len(self._unknown) >= 64:
                    self._unknown.clear()
                self._unknown.add((peer, frame.connection_id))
                self.refuse(peer, "I/O datagram for unknown connection "
                                  f"0x{frame.connection_id:08X} (reported once)", "dropped")
            return
        want = conn.request.o_t_parameters.size - 2
        if len(frame.data) != want:
            self.refuse(peer, f"I/O datagram of {len(frame.data) + 2} bytes on connection "
                              f"0x{conn.o_t_id:08X}, opened for {want + 2}", "dropped")
            return
        conn.last_rx = now
        conn.heard = True
        if conn.last_count is not None and not newer(frame.sequence_count, conn.last_count):
            return  # a repeat or an older packet: not new data (Vol 1, 3-4.4.5)
        conn.last_count = frame.sequence_count
        (header,) = struct.unpack_from("<I", frame.data)
        data = frame.data[4:]
        if header & 1:
            conn.running = True
            self._set_outputs(data, peer, "io")
        elif conn.running or self.outputs != bytes(len(self.outputs)):
            # run → idle: the outputs go to their idle state, as a real adapter's do
            conn.running = False
            self._set_outputs(bytes(self.assemblies.output_size), peer, "idle")

    def _set_outputs(self, data: bytes, peer: str, how: str) -> None:
        self.outputs = bytes(data)
        self._events.append(OutputImage(self.outputs, peer, how))

    def produce(self, now: float, image: bytes) -> list[tuple[bytes, tuple[str, int]]]:
        """The T→O datagrams due at ``now`` with input image ``image`` (the layout's INPUT
        block), and where each goes: every RPI, and on a change connection also when the image
        changed (the RPI then counts from that datagram)."""
        self.inputs = bytes(image)
        out = []
        for conn in self.io_connections():
            if conn.destination is None:
                continue
            due = now >= conn.next_tx
            if not due and not (conn.change_of_state and self.inputs != conn.last_image):
                continue
            conn.encap_sequence = (conn.encap_sequence + 1) & 0xFFFF_FFFF
            conn.sequence_count = (conn.sequence_count + 1) & 0xFFFF
            frame = IoFrame(conn.t_o_id, conn.encap_sequence, conn.sequence_count, self.inputs)
            out.append((frame.pack(), conn.destination))
            conn.last_image = self.inputs
            conn.next_tx = conn.next_tx + conn.api_s if due else now + conn.api_s
            if conn.next_tx <= now:  # late by more than a period: keep the pace from now
                conn.next_tx = now + conn.api_s
        return out

    def watches_changes(self) -> bool:
        """A change-of-state connection is open: the caller offers the image more often."""
        return any(c.change_of_state for c in self.io_connections())

    def next_due(self) -> float | None:
        """When the next T→O datagram is due (None: no class 1 connection)."""
        times = [c.next_tx for c in self.io_connections() if c.destination is not None]
        return min(times) if times else None

    def tick(self, now: float) -> None:
        """Close every connection whose consumer has been silent past its timeout."""
        for conn in list(self.connections.values()):
            limit = conn.timeout_s if conn.heard else max(conn.timeout_s, INITIAL_TIMEOUT_S)
            if now - conn.last_rx > limit:
                self._close(conn, "timed out")

    def _close(self, conn: Connection, why: str) -> None:
        if self.connections.pop(conn.o_t_id, None) is not None:
            self._events.append(ConnectionClosed(conn.peer, conn.transport_class, conn.o_t_id,
                                                 why))

    # --------------------------------------------------------------------- explicit

    def route(self, req: Request, peer: str, now: float, session: TcpSession,
              items: list[Item]) -> tuple[Response, list[Item]]:
        """One Message Router request from ``peer``: the response and any extra CPF items."""
        if req.path.class_id == CONNECTION_MANAGER and req.path.instance == 1:
            if req.service in (Service.FORWARD_OPEN, Service.LARGE_FORWARD_OPEN):
                return self._forward_open(req, peer, now, session, items)
            if req.service == Service.FORWARD_CLOSE:
                return self._forward_close(req, peer), []
            if req.service == Service.UNCONNECTED_SEND:
                try:
                    send = UnconnectedSend.unpack(req.data)
                    inner = Request.unpack(send.request)
                except FrameError as err:
                    self.refuse(peer, f"Unconnected Send: {err}", f"CIP 0x{err.status:02X}")
                    return Response(req.service, err.status), []
                # we are the end of the route: the embedded request is for us
                return self.route(inner, peer, now, session, items)
            return Response(req.service, GeneralStatus.SERVICE_NOT_SUPPORTED), []
        response, change = self.objects.handle(req)
        if response.status:
            self.refuse(peer, f"service 0x{req.service:02X} on class 0x{req.path.class_id or 0:02X}"
                              f" instance {req.path.instance} attribute {req.path.attribute}",
                        f"CIP 0x{response.status:02X}")
        if change is not None:
            self._set_outputs(change.data, peer, "set")
        return response, []

    def _cm_error(self, req: Request, peer: str, what: str, ext: ExtendedStatus,
                  *more: int, general: int = GeneralStatus.CONNECTION_FAILURE) -> Response:
        self.refuse(peer, what, f"CIP 0x{general:02X}/0x{ext:04X}")
        # Forward Open's failure reply carries the connection triple (Vol 1, 3-5.5.2.4)
        data = b""
        if req.service in (Service.FORWARD_OPEN, Service.LARGE_FORWARD_OPEN,
                           Service.FORWARD_CLOSE):
            try:
                triple = (ForwardClose.unpack(_close_view(req.data, req.service)).triple)
                data = struct.pack("<HHIBB", *triple, 0, 0)
            except FrameError:
                data = b""
        return Response(req.service, general, (int(ext), *more), data)

    def _forward_open(self, req: Request, peer: str, now: float, session: TcpSession,
                      items: list[Item]) -> tuple[Response, list[Item]]:
        large = req.service == Service.LARGE_FORWARD_OPEN
        try:
            fo = ForwardOpen.unpack(req.data, large)
        except FrameError as err:
            self.refuse(peer, f"Forward Open: {err}", f"CIP 0x{err.status:02X}")
            return Response(req.service, err.status), []
        found = refusal(fo, self.identity, self.assemblies, self.limits,
                        open_connections=len(self.connections),
                        duplicate=any(c.request.triple == fo.triple
                                      for c in self.connections.values()),
                        owned=self.owned())
        if found is not None:
            return self._cm_error(req, peer, f"Forward Open: {found.text}", found.status,
                                  *found.more), []
        if fo.transport_class == 3:
            conn = Connection(peer, fo, next(self._ids), fo.t_o_connection_id, fo.timeout_s(),
                              now, session=session)
        else:
            dest = (peer, UDP_IO_PORT)
            for item in items:
                if item.type_id == ItemType.SOCKADDR_T_O:
                    try:
                        sa = SocketAddress.unpack(item.data)
                    except FrameError as err:
                        self.refuse(peer, f"Forward Open: T→O {err}",
                                    f"CIP 0x{GeneralStatus.INVALID_PARAMETER:02X}")
                        return Response(req.service, GeneralStatus.INVALID_PARAMETER), []
                    dest = (peer, sa.port)  # unicast: the originator's own address
            api = fo.t_o_rpi_us / 1e6
            conn = Connection(peer, fo, next(self._ids), fo.t_o_connection_id, fo.timeout_s(),
                              now, destination=dest, api_s=api, next_tx=now)
        self.connections[conn.o_t_id] = conn
        self._events.append(ConnectionOpened(peer, fo.transport_class, conn.o_t_id,
                                             fo.t_o_rpi_us / 1e3))
        reply = ForwardOpenReply(conn.o_t_id, conn.t_o_id, fo.connection_serial,
                                 fo.originator_vendor_id, fo.originator_serial,
                                 fo.o_t_rpi_us, fo.t_o_rpi_us)
        # where the O→T datagrams go: said only when it is not the usual UDP 2222
        extra = [Item(ItemType.SOCKADDR_O_T, SocketAddress(self.udp_port).pack())] \
            if fo.transport_class == 1 and self.udp_port != UDP_IO_PORT else []
        return Response(req.service, data=reply.pack()), extra

    def _forward_close(self, req: Request, peer: str) -> Response:
        try:
            fc = ForwardClose.unpack(req.data)
        except FrameError as err:
            self.refuse(peer, f"Forward Close: {err}", f"CIP 0x{err.status:02X}")
            return Response(req.service, err.status)
        for conn in list(self.connections.values()):
            if conn.request.triple == fc.triple:
                self._close(conn, "forward close")
                return Response(req.service, data=forward_close_reply(fc))
        return self._cm_error(req, peer, f"Forward Close: no connection with serial "
                              f"{fc.connection_serial} vendor {fc.originator_vendor_id} "
                              f"originator {fc.originator_serial}",
                              ExtendedStatus.CONNECTION_NOT_FOUND)

    def session_closed(self, session: TcpSession) -> None:
        """A TCP connection ended: its session and its class 3 connections go (class 1
        connections are not tied to the TCP connection, Vol 2, 3-3.3)."""
        self.sessions.pop(session.handle, None)
        for conn in list(self.connections.values()):
            if conn.session is session:
                self._close(conn, "session closed")

    def new_handle(self) -> int:
        return next(self._handles) | 0x1000_0000


def _close_view(data: bytes, service: int) -> bytes:
    """The connection triple of a Forward Open / Forward Close request in Forward Close form
    (what a failure reply echoes)."""
    if service == Service.FORWARD_CLOSE:
        return data
    if len(data) < 20:
        raise FrameError("too short to carry the connection triple")
    return data[0:2] + data[10:18] + b"\x00\x00"
