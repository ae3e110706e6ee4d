"""The PLC twin's EtherNet/IP port: a class 1 originator (scanner), as a line PLC is to the
adapter. It registers a session, opens an exclusive-owner connection with Forward Open, sends
the output image every RPI with the run/idle header in run mode, and keeps the last input image
the adapter produced. :class:`~drivers.links.twin.PlcTwin` runs the PLC program over it
(:func:`enip_twin`).
"""

from __future__ import annotations

import asyncio
import itertools
import os
import struct

from .. import layout
from ..layout import ByteOrder
from ..twin import PlcTwin, PlcTwinError
from .cip import (
    ForwardClose,
    ForwardOpen,
    ForwardOpenReply,
    NetworkParameters,
    Path,
    Request,
    Response,
    Service,
)
from .codec import (
    Command,
    Encapsulation,
    IoFrame,
    Item,
    ItemType,
    SendData,
    SocketAddress,
    run_idle,
)
from .objects import Assemblies

_serials = itertools.count(1)


class EnipPortError(PlcTwinError):
    """The adapter refused the twin (an encapsulation status or a Forward Open error), or
    stopped producing."""


class _Inputs(asyncio.DatagramProtocol):
    def __init__(self, port: EnipPort) -> None:
        self.port = port

    def datagram_received(self, data: bytes, addr: tuple[str | int, ...]) -> None:
        self.port._received(data)


class EnipPort:
    """A :class:`~drivers.links.twin.PlcPort` over class 1 I/O."""

    byte_order = ByteOrder.LITTLE
    word_order = ByteOrder.LITTLE.word_order

    def __init__(self, host: str, port: int, rpi_ms: float = 4.0, multiplier: int = 5,
                 assemblies: Assemblies | None = None, change_of_state: bool = True) -> None:
        """``change_of_state``: ask the adapter to produce on a change of its inputs too (the
        answer then leaves at once; RPI is the background rate); else cyclic only."""
        self.host = host
        self.port = port
        self.rpi_s = rpi_ms / 1000
        self.multiplier = multiplier
        self.trigger = 0x11 if change_of_state else 0x01  # class 1; change of state or cyclic
        self.assemblies = a = assemblies or Assemblies(input_size=layout.INPUT_SIZE,
                                                       output_size=layout.OUTPUT_SIZE)
        self.outputs = bytearray(a.output_size)
        self.inputs: bytes | None = None
        self._fresh = asyncio.Event()
        self._sent = asyncio.Event()
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._udp: asyncio.DatagramTransport | None = None
        self._producer: asyncio.Task[None] | None = None
        self._session = 0
        self._o_t_id = 0
        self._dest: tuple[str, int] = (host, 2222)
        self._serial = next(_serials)
        self._origin = os.getpid() & 0xFFFF_FFFF
        self._seq = 0
        self._last_count: int | None = None
        self._images = 0  # T→O images received
        self._read = -1  # the image count at the last read_inputs

    # --------------------------------------------------------------------- PlcPort

    async def connect(self) -> None:
        """Session, UDP socket, Forward Open, first image; EnipPortError when refused."""
        loop = asyncio.get_running_loop()
        self._reader, self._writer = await asyncio.open_connection(self.host, self.port)
        reply = await self._ask(Encapsulation(Command.REGISTER_SESSION,
                                              data=struct.pack("<HH", 1, 0)))
        self._session = reply.session_handle
        udp, _ = await loop.create_datagram_endpoint(lambda: _Inputs(self),
                                                     local_addr=(self.host, 0))
        self._udp = udp
        local_port = int(udp.get_extra_info("sockname")[1])
        a = self.assemblies
        rpi_us = round(self.rpi_s * 1e6)
        fo = ForwardOpen(
            0, 0x7000_0000 | self._serial, self._serial, 0xFFFF, self._origin,
            self.multiplier, rpi_us, NetworkParameters(a.output_size + 6), rpi_us,
            NetworkParameters(a.input_size + 2), self.trigger,
            Path(class_id=4, instance=a.config_instance,
                 points=(a.output_instance, a.input_instance)))
        response, items = await self._cm(Service.FORWARD_OPEN, fo.pack(),
                                         [Item(ItemType.SOCKADDR_T_O,
                                               SocketAddress(local_port).pack())])
        opened = ForwardOpenReply.unpack(response.data)
        self._o_t_id = opened.o_t_connection_id
        for item in items:
            if item.type_id == ItemType.SOCKADDR_O_T:
                self._dest = (self.host, SocketAddress.unpack(item.data).port)
        self._producer = asyncio.create_task(self._produce(), name="enip-twin-io")
        await self.read_inputs()

    async def read_inputs(self) -> bytes:
        """The input image as the PLC holds it: a newer one than the last read's, as a PLC
        program's next scan after the next RPI sees it (so a program that polls does not spin).
        EnipPortError when none comes within 50 RPIs (at least 5 s, past a loaded machine's
        stalls): the adapter is gone."""
        limit = max(5.0, 50 * self.rpi_s)
        while self.inputs is None or self._images == self._read:
            self._fresh.clear()
            try:
                await asyncio.wait_for(self._fresh.wait(), limit)
            except TimeoutError:
                raise EnipPortError(f"EtherNet/IP adapter {self.host}:{self.port}: no input "
                                    f"image within {limit:g} s") from None
        self._read = self._images
        return self.inputs

    async def write_outputs(self, offset: int, data: bytes) -> None:
        """Change part of the output image; returns once a datagram carrying it has left."""
        if offset < 0 or offset + len(data) > len(self.outputs):
            raise ValueError(f"outputs {offset}..{offset + len(data)} outside the "
                             f"{len(self.outputs)}-byte output assembly")
        self.outputs[offset : offset + len(data)] = data
        self._sent.clear()
        await asyncio.wait_for(self._sent.wait(), 5.0)

    def close(self) -> None:
        """Forward Close and UnRegisterSession, as a PLC that closes its connection (the
        requests are sent, the replies not awaited: the TCP close flushes them first)."""
        if self._writer is not None and not self._writer.is_closing() and self._session:
            a = self.assemblies
            fc = ForwardClose(self._serial, 0xFFFF, self._origin,
                              Path(class_id=4, instance=a.config_instance,
                                   points=(a.output_instance, a.input_instance)))
            self._writer.write(self._rr(Service.FORWARD_CLOSE, fc.pack(), []).pack())
            self._writer.write(Encapsulation(Command.UNREGISTER_SESSION, self._session).pack())
        self.abort()

    def abort(self) -> None:
        """Drop everything without a word, as a PLC losing power: the adapter's connection
        times out."""
        if self._producer is not None:
            self._producer.cancel()
            self._producer = None
        if self._udp is not None:
            self._udp.close()
            self._udp = None
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    # --------------------------------------------------------------------- inside

    async def _produce(self) -> None:
        loop = asyncio.get_running_loop()
        next_tx = loop.time()
        while self._udp is not None:
            self._seq += 1
            frame = IoFrame(self._o_t_id, self._seq, self._seq & 0xFFFF,
                            run_idle(True) + bytes(self.outputs))
            self._udp.sendto(frame.pack(), self._dest)
            self._sent.set()
            next_tx += self.rpi_s
            await asyncio.sleep(max(0.0, next_tx - loop.time()))

    def _received(self, data: bytes) -> None:
        try:
            frame = IoFrame.unpack(data)
        except ValueError:
            return
        if self._last_count is not None and frame.sequence_count == self._last_count:
            return
        self._last_count = frame.sequence_count
        self.inputs = frame.data
        self._images += 1
        self._fresh.set()

    async def _ask(self, msg: Encapsulation) -> Encapsulation:
        assert self._reader is not None and self._writer is not None
        self._writer.write(msg.pack())
        head = await asyncio.wait_for(self._reader.readexactly(24), 5.0)
        rest = await self._reader.readexactly(Encapsulation.length_of(head) - 24)
        reply = Encapsulation.unpack(head + rest)
        if reply.status:
            raise EnipPortError(f"EtherNet/IP adapter {self.host}:{self.port}: command "
                                f"0x{msg.command:04X} answered status 0x{reply.status:04X}")
        return reply

    def _rr(self, service: int, data: bytes, extra: list[Item]) -> Encapsulation:
        """A Connection Manager request in SendRRData (UCMM)."""
        req = Request(service, Path(class_id=6, instance=1), data)
        send = SendData([Item(ItemType.NULL_ADDRESS), Item(ItemType.UNCONNECTED_DATA,
                                                            req.pack()), *extra])
        return Encapsulation(Command.SEND_RR_DATA, self._session, data=send.pack())

    async def _cm(self, service: int, data: bytes, extra: list[Item]
                  ) -> tuple[Response, list[Item]]:
        reply = await self._ask(self._rr(service, data, extra))
        items = SendData.unpack(reply.data).items
        response = Response.unpack(items[1].data)
        if response.status:
            ext = ", ".join(f"0x{w:04X}" for w in response.extended)
            raise EnipPortError(f"EtherNet/IP adapter {self.host}:{self.port}: service "
                                f"0x{service:02X} answered CIP 0x{response.status:02X} ({ext})")
        return response, items[2:]


def enip_twin(host: str, port: int, *, rpi_ms: float = 4.0, multiplier: int = 7,
              poll_s: float = 0.0, change_of_state: bool = True) -> PlcTwin:
    """A PLC twin on EtherNet/IP class 1 I/O (RPI ``rpi_ms``, timeout RPI × 4 << multiplier:
    2.048 s by default, past the stalls of a loaded test machine, as a PLC's 100 ms floor is
    past a busy network's)."""
    return PlcTwin(EnipPort(host, port, rpi_ms=rpi_ms, multiplier=multiplier,
                            change_of_state=change_of_state), poll_s=poll_s)
