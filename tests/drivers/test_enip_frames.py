"""The EtherNet/IP adapter's protocol core without sockets: bytes in, replies and events out.

Requests are written as the specification lays them out (byte literals, with the section they
follow), so a mistake shared by our encoder and decoder cannot cancel itself out.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

from drivers.links.enip.adapter import (
    Adapter,
    ConnectionClosed,
    ConnectionOpened,
    OutputImage,
    Refused,
)
from drivers.links.enip.admission import Limits
from drivers.links.enip.cip import ForwardOpen, NetworkParameters, Path, Request, Response
from drivers.links.enip.codec import (
    Encapsulation,
    FrameError,
    Identity,
    IoFrame,
    Item,
    SendData,
    unpack_items,
)
from drivers.links.enip.session import TcpSession

IDENTITY = Identity(vendor_id=0xFFFF, device_type=0x2B, product_code=1, revision=(1, 2),
                    serial_number=0x12345678, product_name="mvpose station")
CTX = b"ctx-0001"


def adapter(**limits: int) -> Adapter:
    return Adapter(IDENTITY, limits=Limits(**limits), udp_port=40000)


def encap(command: int, data: bytes = b"", session: int = 0) -> bytes:
    # Vol 2, 2-3.1: command, length, session handle, status, sender context, options
    return struct.pack("<HHII8sI", command, len(data), session, 0, CTX, 0) + data


def registered(a: Adapter, peer: str = "10.0.0.5") -> TcpSession:
    s = a.session(peer)
    (raw,) = s.receive_data(encap(0x65, b"\x01\x00\x00\x00"), 0.0)
    reply = Encapsulation.unpack(raw)
    assert reply.status == 0 and reply.session_handle == s.handle != 0
    return s


def rr(s: TcpSession, mr_request: bytes, now: float = 0.0, *extra: Item) -> SendData:
    """A UCMM request through SendRRData (Vol 2, 2-4.7): null address + unconnected data."""
    cpf = struct.pack("<HHHHH", 2 + len(extra), 0, 0, 0xB2, len(mr_request)) + mr_request
    cpf += b"".join(i.pack() for i in extra)
    (raw,) = s.receive_data(encap(0x6F, struct.pack("<IH", 0, 0) + cpf, s.handle), now)
    reply = Encapsulation.unpack(raw)
    assert reply.status == 0, hex(reply.status)
    assert reply.sender_context == CTX
    return SendData.unpack(reply.data)


def answer(send: SendData) -> Response:
    return Response.unpack(send.items[1].data)


def forward_open(ot_size: int = 86, to_size: int = 170, rpi_us: int = 4000, serial: int = 7,
                 path: bytes = b"\x20\x04\x24\x97\x2c\x96\x2c\x64", transport: int = 0x01,
                 large: bool = False, multiplier: int = 0) -> bytes:
    """Forward Open request data (Vol 1, 3-5.5.2), written field by field: path class 4,
    config instance 151, connection points 150 (O→T) and 100 (T→O)."""
    params = "I" if large else "H"
    ot = (ot_size | 2 << 26 | 2 << 29) if large else (ot_size | 2 << 10 | 2 << 13)
    to = (to_size | 2 << 26 | 2 << 29) if large else (to_size | 2 << 10 | 2 << 13)
    return struct.pack(f"<BBIIHHIB3sI{params}I{params}BB", 0x0A, 0xF0, 0, 0xBEEF0001, serial,
                       0x1234, 0xCAFE, multiplier, b"\0\0\0", rpi_us, ot, rpi_us, to, transport,
                       len(path) // 2) + path


def cm(service: int, data: bytes) -> bytes:
    return bytes([service, 2, 0x20, 0x06, 0x24, 0x01]) + data  # Connection Manager, instance 1


def io(conn_id: int, count: int, data: bytes, run: bool = True, seq: int = 1) -> bytes:
    """An O→T datagram (Vol 2, 3-2.1): sequenced address item, connected data item with the
    sequence count and the 32-bit run/idle header."""
    body = struct.pack("<HI", count, 1 if run else 0) + data
    return struct.pack("<HHHIIHH", 2, 0x8002, 8, conn_id, seq, 0xB1, len(body)) + body


def opened(a: Adapter, s: TcpSession, **kw: int) -> int:
    reply = rr(s, cm(0x54, forward_open(**kw)), 0.0, Item(0x8001, struct.pack(
        ">hHI8s", 2, 50000, 0, bytes(8))))
    r = answer(reply)
    assert r.status == 0, (hex(r.status), r.extended)
    ot_id, to_id = struct.unpack_from("<II", r.data)
    assert to_id == 0xBEEF0001  # point to point: the originator's T→O id (Vol 2, 3-3.7.1)
    # the adapter's I/O port is not 2222: the reply says where O→T datagrams go
    sockaddr = [i for i in reply.items if i.type_id == 0x8000]
    assert sockaddr and struct.unpack(">hH", sockaddr[0].data[:4]) == (2, a.udp_port)
    return int(ot_id)


# ---------------------------------------------------------------------------- encapsulation


def test_register_session_then_list_identity_and_services() -> None:
    a = adapter()
    s = registered(a)
    (raw,) = s.receive_data(encap(0x63), 0.0)
    items = unpack_items(Encapsulation.unpack(raw).data)
    assert items[0].type_id == 0x0C
    body = items[0].data
    # version, sockaddr (16, big-endian), vendor, device type, product code, revision
    assert struct.unpack_from("<H", body) == (1,)
    assert struct.unpack_from(">hH", body, 2) == (2, 44818)
    assert struct.unpack_from("<HHHBBHI", body, 18) == (0xFFFF, 0x2B, 1, 1, 2, 0, 0x12345678)
    assert body[33 : 33 + body[32]] == b"mvpose station"
    (raw,) = s.receive_data(encap(0x04), 0.0)
    (svc,) = unpack_items(Encapsulation.unpack(raw).data)
    assert svc.type_id == 0x100 and struct.unpack_from("<HH", svc.data) == (1, 0x0120)


def test_the_usual_io_port_is_not_repeated_in_the_reply() -> None:
    a = Adapter(IDENTITY, udp_port=2222)
    reply = rr(registered(a), cm(0x54, forward_open()))
    assert answer(reply).status == 0
    assert [i.type_id for i in reply.items] == [0, 0xB2]


def test_listidentity_on_udp_answers_and_other_commands_are_dropped() -> None:
    a = adapter()
    reply = a.receive_udp_encapsulation(encap(0x63), "10.0.0.9")
    assert reply is not None and Encapsulation.unpack(reply).command == 0x63
    assert a.receive_udp_encapsulation(encap(0x65, b"\1\0\0\0"), "10.0.0.9") is None
    assert a.receive_udp_encapsulation(b"\x63\x00", "10.0.0.9") is None
    assert all(isinstance(e, Refused) and e.peer == "10.0.0.9" for e in a.events())


def test_messages_split_across_reads_are_joined() -> None:
    a = adapter()
    s = a.session("10.0.0.5")
    raw = encap(0x65, b"\x01\x00\x00\x00") + encap(0x63)
    assert s.receive_data(raw[:10], 0.0) == []
    replies = s.receive_data(raw[10:30], 0.0) + s.receive_data(raw[30:], 0.0)
    assert [Encapsulation.unpack(r).command for r in replies] == [0x65, 0x63]


def test_unknown_session_handle_gets_status_0x64_and_a_refusal_naming_the_peer() -> None:
    a = adapter()
    s = registered(a)
    (raw,) = s.receive_data(encap(0x6F, bytes(6) + b"\x00\x00", s.handle + 1), 0.0)
    assert Encapsulation.unpack(raw).status == 0x64
    (ev,) = a.events()
    assert isinstance(ev, Refused) and ev.peer == "10.0.0.5" and "0x0064" in ev.status
    assert not s.closed


def test_malformed_encapsulation_gets_its_status() -> None:
    a = adapter()
    s = registered(a)
    # unknown command → 0x0001; a common packet format that lies about its length → 0x0003
    (raw,) = s.receive_data(encap(0x99), 0.0)
    assert Encapsulation.unpack(raw).status == 0x01
    bad_cpf = struct.pack("<IHHHH", 0, 0, 2, 0, 0) + struct.pack("<HH", 0xB2, 40) + b"\x0e"
    (raw,) = s.receive_data(encap(0x6F, bad_cpf, s.handle), 0.0)
    assert Encapsulation.unpack(raw).status == 0x03
    # RegisterSession of another protocol version → 0x0069 with the version we speak
    (raw,) = a.session("10.0.0.6").receive_data(encap(0x65, b"\x02\x00\x00\x00"), 0.0)
    reply = Encapsulation.unpack(raw)
    assert reply.status == 0x69 and reply.data == b"\x01\x00\x00\x00"
    # a length past the limit → 0x0065, and the connection is to be closed
    s2 = a.session("10.0.0.7")
    (raw,) = s2.receive_data(struct.pack("<HHII8sI", 0x6F, 60000, 0, 0, CTX, 0), 0.0)
    assert Encapsulation.unpack(raw).status == 0x65 and s2.closed
    assert len([e for e in a.events() if isinstance(e, Refused)]) == 4


def test_session_limit_answers_insufficient_memory() -> None:
    a = adapter(max_sessions=1)
    registered(a)
    (raw,) = a.session("10.0.0.6").receive_data(encap(0x65, b"\x01\x00\x00\x00"), 0.0)
    assert Encapsulation.unpack(raw).status == 0x02


# ---------------------------------------------------------------------------- explicit


def test_get_attribute_single_on_the_assemblies_and_identity() -> None:
    a = adapter()
    s = registered(a)
    a.produce(0.0, bytes(range(168)))
    # Get_Attribute_Single (0x0E), class 4 instance 100 attribute 3
    r = answer(rr(s, b"\x0e\x03\x20\x04\x24\x64\x30\x03"))
    assert r.status == 0 and r.data == bytes(range(168))
    r = answer(rr(s, b"\x0e\x03\x20\x04\x24\x96\x30\x04"))  # output assembly's size
    assert r.data == struct.pack("<H", 80)
    r = answer(rr(s, b"\x01\x02\x20\x01\x24\x01"))  # Identity Get_Attributes_All
    assert struct.unpack_from("<HHH", r.data) == (0xFFFF, 0x2B, 1)
    r = answer(rr(s, b"\x0e\x03\x20\xf5\x24\x01\x30\x04"))  # TCP/IP: link object path
    assert r.data == b"\x02\x00\x20\xf6\x24\x01"
    r = answer(rr(s, b"\x0e\x03\x20\xf6\x24\x01\x30\x01"))  # Ethernet Link: speed
    assert struct.unpack("<I", r.data) == (100,)


def test_set_attribute_single_writes_the_outputs_and_refuses_the_inputs() -> None:
    a = adapter()
    s = registered(a)
    r = answer(rr(s, b"\x10\x03\x20\x04\x24\x96\x30\x03" + bytes([7] * 80)))
    assert r.status == 0
    (ev,) = a.events()
    assert isinstance(ev, OutputImage) and ev.data == bytes([7] * 80) and ev.how == "set"
    r = answer(rr(s, b"\x10\x03\x20\x04\x24\x64\x30\x03" + bytes(168)))
    assert r.status == 0x0E  # attribute not settable
    r = answer(rr(s, b"\x10\x03\x20\x04\x24\x96\x30\x03" + bytes(79)))
    assert r.status == 0x13  # not enough data
    r = answer(rr(s, b"\x10\x03\x20\x04\x24\x96\x30\x03" + bytes(81)))
    assert r.status == 0x15  # too much data
    r = answer(rr(s, b"\x0e\x03\x20\x04\x24\x09\x30\x03"))
    assert r.status == 0x16  # no assembly instance 9
    events = a.events()
    assert len(events) == 4 and all(isinstance(e, Refused) for e in events)
    assert a.outputs == bytes([7] * 80)  # nothing of the refused writes was taken


def test_unconnected_send_reaches_the_embedded_request() -> None:
    a = adapter()
    s = registered(a)
    inner = b"\x0e\x03\x20\x04\x24\x96\x30\x04"
    # Vol 1, 3-5.5.4: tick, ticks, size, request, route path size, reserved, route (port 1 slot 0)
    data = struct.pack("<BBH", 0x0A, 0xF0, len(inner)) + inner + b"\x01\x00\x01\x00"
    r = answer(rr(s, cm(0x52, data)))
    assert r.service == 0x0E and r.data == struct.pack("<H", 80)


def test_class3_connection_carries_explicit_requests() -> None:
    a = adapter()
    s = registered(a)
    fo = forward_open(ot_size=504, to_size=504, transport=0xA3, rpi_us=2_000_000,
                      path=b"\x20\x02\x24\x01", large=True, multiplier=3)
    r = answer(rr(s, cm(0x5B, fo)))
    assert r.status == 0
    ot_id = struct.unpack_from("<I", r.data)[0]
    req = b"\x0e\x03\x20\x04\x24\x96\x30\x04"
    cpf = struct.pack("<HHHIHHH", 2, 0xA1, 4, ot_id, 0xB1, 2 + len(req), 5) + req
    (raw,) = s.receive_data(encap(0x70, struct.pack("<IH", 0, 0) + cpf, s.handle), 0.0)
    items = SendData.unpack(Encapsulation.unpack(raw).data).items
    assert items[0].data == struct.pack("<I", 0xBEEF0001)
    assert items[1].data[:2] == struct.pack("<H", 5)  # the sequence count is echoed
    assert Response.unpack(items[1].data[2:]).data == struct.pack("<H", 80)
    s.close()  # the session's class 3 connections go with it
    assert not a.connections
    assert any(isinstance(e, ConnectionClosed) and e.why == "session closed"
               for e in a.events())


# ---------------------------------------------------------------------------- class 1


def test_forward_open_io_produce_consume_and_forward_close() -> None:
    a = adapter()
    s = registered(a)
    ot_id = opened(a, s)
    (ev,) = a.events()
    assert isinstance(ev, ConnectionOpened) and ev.transport_class == 1 and ev.rpi_ms == 4.0
    out = a.produce(0.0, bytes([1] * 168))
    assert [dest for _, dest in out] == [("10.0.0.5", 50000)]
    frame = IoFrame.unpack(out[0][0])
    assert (frame.connection_id, frame.sequence_count, frame.data) == (0xBEEF0001, 1,
                                                                       bytes([1] * 168))
    assert a.produce(0.001, bytes(168)) == []  # not due before the RPI
    again = IoFrame.unpack(a.produce(0.004, bytes(168))[0][0])
    assert again.sequence_count == 2 and again.encap_sequence == frame.encap_sequence + 1
    a.receive_io(io(ot_id, 1, bytes([9] * 80)), "10.0.0.5", 0.005)
    a.receive_io(io(ot_id, 1, bytes([8] * 80)), "10.0.0.5", 0.006)  # same count: not new
    a.receive_io(io(ot_id, 2, bytes([8] * 80)), "10.0.0.5", 0.007)
    images = [e.data for e in a.events() if isinstance(e, OutputImage)]
    assert images == [bytes([9] * 80), bytes([8] * 80)]
    # an explicit Set while an exclusive owner holds the outputs: object state conflict
    assert answer(rr(s, b"\x10\x03\x20\x04\x24\x96\x30\x03" + bytes(80))).status == 0x0C
    close = struct.pack("<BBHHIBB", 0x0A, 0xF0, 7, 0x1234, 0xCAFE, 4, 0) \
        + b"\x20\x04\x24\x97\x2c\x96\x2c\x64"
    r = answer(rr(s, cm(0x4E, close)))
    assert r.status == 0 and struct.unpack_from("<HHI", r.data) == (7, 0x1234, 0xCAFE)
    assert not a.connections and a.produce(1.0, bytes(168)) == []
    r = answer(rr(s, cm(0x4E, close)))
    assert (r.status, r.extended) == (0x01, (0x0107,))


def test_change_of_state_produces_on_a_change_and_every_rpi() -> None:
    a = adapter()
    s = registered(a)
    opened(a, s, transport=0x11)  # class 1, production trigger change of state
    assert a.watches_changes()
    assert len(a.produce(0.0, bytes(168))) == 1  # the first one is due at once
    assert a.produce(0.001, bytes(168)) == []  # nothing changed, not due
    (changed,) = a.produce(0.002, bytes([1]) + bytes(139))  # a change leaves at once
    assert IoFrame.unpack(changed[0]).sequence_count == 2
    assert a.produce(0.005, bytes([1]) + bytes(139)) == []  # the RPI counts from the change
    assert len(a.produce(0.006, bytes([1]) + bytes(139))) == 1
    r = answer(rr(s, cm(0x54, forward_open(serial=8, transport=0x21))))
    assert r.extended == (0x0103,)  # application triggered: not supported


def test_run_to_idle_clears_the_outputs() -> None:
    a = adapter()
    s = registered(a)
    ot_id = opened(a, s)
    a.receive_io(io(ot_id, 1, bytes([5] * 80)), "10.0.0.5", 0.004)
    a.receive_io(io(ot_id, 2, bytes([5] * 80), run=False), "10.0.0.5", 0.008)
    images = [(e.data, e.how) for e in a.events() if isinstance(e, OutputImage)]
    assert images == [(bytes([5] * 80), "io"), (bytes(80), "idle")]


def test_silent_consumer_times_out_after_rpi_times_multiplier() -> None:
    a = adapter()
    s = registered(a)
    ot_id = opened(a, s, rpi_us=10_000, multiplier=1)  # 10 ms × 8 = 80 ms
    a.tick(9.9)  # until the first packet, the watchdog runs 10 s (CIP's initial timeout)
    assert a.connections
    a.receive_io(io(ot_id, 1, bytes(80)), "10.0.0.5", 9.9)
    a.tick(9.979)
    assert a.connections
    a.tick(9.981)
    assert not a.connections
    closed = [e for e in a.events() if isinstance(e, ConnectionClosed)]
    assert closed and closed[0].why == "timed out"


@pytest.mark.parametrize(("kw", "ext", "more"), [
    ({"ot_size": 84}, 0x0127, (86,)),
    ({"to_size": 200}, 0x0128, (170,)),
    ({"rpi_us": 1000}, 0x0111, ()),
    ({"path": b"\x20\x04\x24\x97\x2c\x95\x2c\x64"}, 0x0117, ()),
    ({"transport": 0x02}, 0x0103, ()),
])
def test_forward_open_errors(kw: dict[str, int], ext: int, more: tuple[int, ...]) -> None:
    a = adapter()
    s = registered(a)
    r = answer(rr(s, cm(0x54, forward_open(**kw))))  # type: ignore[arg-type]
    assert (r.status, r.extended) == (0x01, (ext, *more))
    assert struct.unpack_from("<HHI", r.data) == (7, 0x1234, 0xCAFE)  # the triple is echoed
    (ev,) = a.events()
    assert isinstance(ev, Refused) and ev.peer == "10.0.0.5" and f"0x{ext:04X}" in ev.status
    assert not a.connections


def test_ownership_and_connection_limit() -> None:
    a = adapter(max_connections=2)
    s = registered(a)
    opened(a, s)
    r = answer(rr(s, cm(0x54, forward_open(serial=8))))
    assert r.extended == (0x0106,)  # a second exclusive owner
    r = answer(rr(s, cm(0x54, forward_open(serial=7))))
    assert r.extended == (0x0100,)  # the same triple again
    class3 = {"transport": 0xA3, "rpi_us": 2_000_000, "path": b"\x20\x02\x24\x01",
              "ot_size": 500, "to_size": 500}
    assert answer(rr(s, cm(0x54, forward_open(serial=9, **class3)))).status == 0
    r = answer(rr(s, cm(0x54, forward_open(serial=10, **class3))))
    assert (r.status, r.extended) == (0x01, (0x0113,))  # out of connections


def test_unknown_or_short_io_datagrams_are_dropped() -> None:
    a = adapter()
    s = registered(a)
    ot_id = opened(a, s)
    a.events()
    a.receive_io(io(ot_id + 1, 1, bytes(80)), "10.0.0.5", 0.0)
    a.receive_io(io(ot_id + 1, 2, bytes(80)), "10.0.0.5", 0.0)  # reported once, not per packet
    a.receive_io(io(ot_id, 1, bytes(70)), "10.0.0.5", 0.0)
    a.receive_io(b"\x02\x00", "10.0.0.5", 0.0)
    a.receive_io(io(ot_id, 1, bytes(80)), "10.0.0.66", 0.0)  # another host
    events = a.events()
    assert len(events) == 4 and all(isinstance(e, Refused) for e in events)
    assert a.outputs == bytes(80)


# ---------------------------------------------------------------------------- frames


def test_frames_round_trip() -> None:
    fo = ForwardOpen(1, 2, 3, 4, 5, 2, 4000, NetworkParameters(86), 4000,
                     NetworkParameters(170), 1,
                     Path(class_id=4, instance=151, points=(150, 100),
                          key=(0, 0, 0, 0, 0)), large=True)
    assert ForwardOpen.unpack(fo.pack(), large=True) == fo
    assert fo.timeout_s() == pytest.approx(0.064)
    req = Request(0x0E, Path(class_id=0x104, instance=300, attribute=3))
    assert Request.unpack(req.pack()) == req
    frame = IoFrame(9, 10, 11, b"abc")
    assert IoFrame.unpack(frame.pack()) == frame
    with pytest.raises(FrameError, match="segment 0x.. at byte 0"):
        Path.unpack(b"\xe0\x00")


def test_random_requests_get_answers_never_exceptions() -> None:
    """Garbage inside well-framed messages: every one is answered (or dropped) with a status;
    nothing raises out of the core."""
    rng = np.random.default_rng(24)
    a = adapter()
    s = registered(a)
    for n in range(3000):
        kind = n % 4
        body = rng.integers(0, 256, int(rng.integers(0, 80))).astype(np.uint8).tobytes()
        if kind == 0:  # a message router request with a random path and data
            mr = bytes([int(rng.integers(0, 256)), len(body) // 4]) + body
            cpf = struct.pack("<HHHHH", 2, 0, 0, 0xB2, len(mr)) + mr
            raw = encap(0x6F, struct.pack("<IH", 0, 0) + cpf, s.handle)
        elif kind == 1:  # a Forward Open / Close / Unconnected Send with random data
            service = int(rng.choice([0x54, 0x5B, 0x4E, 0x52]))
            mr = cm(service, body)
            cpf = struct.pack("<HHHHH", 2, 0, 0, 0xB2, len(mr)) + mr
            raw = encap(0x6F, struct.pack("<IH", 0, 0) + cpf, s.handle)
        elif kind == 2:  # random command data
            raw = encap(int(rng.choice([0x04, 0x63, 0x6F, 0x70, 0x65])), body, s.handle)
        else:  # a random I/O datagram
            a.receive_io(body, "10.0.0.5", 0.0)
            continue
        s.receive_data(raw, 0.0)
        if s.closed:
            s = registered(a)
    assert a.events()  # the refusals were reported
