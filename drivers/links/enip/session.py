"""One TCP connection's encapsulation (Vol 2, chapter 2) in the adapter's sans-I/O core:
framing of the byte stream, RegisterSession / UnRegisterSession, the List commands, and
SendRRData / SendUnitData handed to the :class:`~.adapter.Adapter`'s Message Router.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .cip import Request, Response
from .codec import (
    Command,
    EncapStatus,
    Encapsulation,
    FrameError,
    Item,
    ItemType,
    SendData,
    list_services_item,
    pack_items,
)

if TYPE_CHECKING:
    from .adapter import Adapter

MAX_MESSAGE = 4096  # encapsulation data longer than this is refused (INVALID_LENGTH)



@dataclass
class TcpSession:
    """One TCP connection's encapsulation state (Vol 2, 2-2)."""

    adapter: Adapter
    peer: str
    handle: int = 0
    closed: bool = False
    _buffer: bytearray = field(default_factory=bytearray)

    def receive_data(self, data: bytes, now: float) -> list[bytes]:
        """Bytes from the peer: the replies to send, in order. After a message that ends the
        session (UnRegisterSession, a length past the limit), ``closed`` is True and the
        caller closes the TCP connection."""
        self._buffer += data
        out: list[bytes] = []
        while not self.closed and len(self._buffer) >= 24:
            length = Encapsulation.length_of(bytes(self._buffer[:24]))
            if length - 24 > MAX_MESSAGE:
                command = int.from_bytes(self._buffer[0:2], "little")
                ctx = bytes(self._buffer[12:20])
                self.adapter.refuse(self.peer, f"encapsulation of {length - 24} bytes (limit "
                                    f"{MAX_MESSAGE})", "encapsulation status 0x0065")
                out.append(Encapsulation(command, 0, EncapStatus.INVALID_LENGTH, ctx).pack())
                self.close()
                break
            if len(self._buffer) < length:
                break
            raw = bytes(self._buffer[:length])
            del self._buffer[:length]
            reply = self._message(Encapsulation.unpack(raw), now)
            if reply is not None:
                out.append(reply.pack())
        return out

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.adapter.session_closed(self)

    def _status(self, msg: Encapsulation, status: EncapStatus, what: str) -> Encapsulation:
        self.adapter.refuse(self.peer, what, f"encapsulation status 0x{status:04X}")
        return msg.reply(status=status)

    def _message(self, msg: Encapsulation, now: float) -> Encapsulation | None:
        a = self.adapter
        if msg.command == Command.NOP:
            return None
        if msg.command == Command.LIST_IDENTITY:
            return msg.reply(a.list_identity())
        if msg.command == Command.LIST_SERVICES:
            return msg.reply(pack_items([list_services_item()]))
        if msg.command == Command.LIST_INTERFACES:
            return msg.reply(struct.pack("<H", 0))
        if msg.command == Command.REGISTER_SESSION:
            return self._register(msg)
        if msg.command in (Command.UNREGISTER_SESSION, Command.SEND_RR_DATA,
                           Command.SEND_UNIT_DATA):
            if not self.handle or msg.session_handle != self.handle:
                return self._status(msg, EncapStatus.INVALID_SESSION,
                                    f"command 0x{msg.command:04X} with session handle "
                                    f"0x{msg.session_handle:08X}, not this connection's")
            if msg.command == Command.UNREGISTER_SESSION:
                self.close()
                return None
            try:
                send = SendData.unpack(msg.data)
                if msg.command == Command.SEND_RR_DATA:
                    return msg.reply(self._unconnected(send, now).pack())
                return msg.reply(self._connected(send, now).pack())
            except FrameError as err:
                return self._status(msg, EncapStatus.INCORRECT_DATA,
                                    f"command 0x{msg.command:04X}: {err}")
        return self._status(msg, EncapStatus.INVALID_COMMAND,
                            f"unknown encapsulation command 0x{msg.command:04X}")

    def _register(self, msg: Encapsulation) -> Encapsulation:
        a = self.adapter
        if len(msg.data) != 4:
            return self._status(msg, EncapStatus.INVALID_LENGTH,
                                f"RegisterSession with {len(msg.data)} bytes of data, need 4")
        version, options = struct.unpack("<HH", msg.data)
        if version != 1 or options:
            a.refuse(self.peer, f"RegisterSession protocol version {version} options {options}",
                     "encapsulation status 0x0069")
            return msg.reply(struct.pack("<HH", 1, 0), EncapStatus.UNSUPPORTED_PROTOCOL)
        if self.handle:
            return self._status(msg, EncapStatus.INVALID_COMMAND,
                                "RegisterSession on a connection that has a session")
        if len(a.sessions) >= a.limits.max_sessions:
            return self._status(msg, EncapStatus.INSUFFICIENT_MEMORY,
                                f"RegisterSession: {len(a.sessions)} sessions open, the limit "
                                f"is {a.limits.max_sessions}")
        self.handle = a.new_handle()
        a.sessions[self.handle] = self
        return msg.reply(msg.data, session=self.handle)

    def _unconnected(self, send: SendData, now: float) -> SendData:
        items = send.items
        if len(items) < 2 or items[0].type_id != ItemType.NULL_ADDRESS \
                or items[1].type_id != ItemType.UNCONNECTED_DATA:
            raise FrameError("SendRRData needs a null address item and an unconnected data item")
        req = Request.unpack(items[1].data)
        response, extra = self.adapter.route(req, self.peer, now, self, items[2:])
        return SendData([Item(ItemType.NULL_ADDRESS), Item(ItemType.UNCONNECTED_DATA,
                                                            response.pack()), *extra])

    def _connected(self, send: SendData, now: float) -> SendData:
        items = send.items
        if len(items) != 2 or items[0].type_id != ItemType.CONNECTED_ADDRESS \
                or items[1].type_id != ItemType.CONNECTED_DATA or len(items[0].data) != 4 \
                or len(items[1].data) < 2:
            raise FrameError("SendUnitData needs a connected address item and a connected "
                             "data item")
        (conn_id,) = struct.unpack("<I", items[0].data)
        conn = self.adapter.connections.get(conn_id)
        if conn is None or conn.transport_class != 3 or conn.session is not self:
            raise FrameError(f"SendUnitData for connection 0x{conn_id:08X}, not a class 3 "
                             "connection of this session")
        conn.last_rx = now
        conn.heard = True
        count, body = items[1].data[:2], items[1].data[2:]
        try:
            req = Request.unpack(body)
            response, _ = self.adapter.route(req, self.peer, now, self, [])
        except FrameError as err:
            self.adapter.refuse(self.peer, f"class 3 request: {err}", f"CIP 0x{err.status:02X}")
            response = Response(body[0] if body else 0, err.status)
        return SendData([Item(ItemType.CONNECTED_ADDRESS, struct.pack("<I", conn.t_o_id)),
                         Item(ItemType.CONNECTED_DATA, count + response.pack())])
