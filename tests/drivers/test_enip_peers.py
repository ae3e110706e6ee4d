"""The EtherNet/IP adapter on loopback, driven by peers we did not write: pycomm3 (explicit
messages, UCMM and class 3, ListIdentity) and the PyPI scanner ``ethernetip`` (class 1 I/O:
Forward Open, cyclic UDP both ways, Forward Close).

``ethernetip`` connects to the ports in its module constants; the tests point them at the
adapter's free ports (the adapter answers on any port, a scanner library that cannot choose one
is what there is)."""

from __future__ import annotations

import asyncio
import socket
import struct
from collections.abc import AsyncIterator, Iterator

import ethernetip.ethernetip as scanner
import pytest
from pycomm3 import CIPDriver

from drivers.links.enip.codec import Identity
from drivers.links.enip.transport import EnipServer
from tests.waiting import until

ID = Identity(0xFFFF, 0x2B, 1, (1, 1), 0x0BADF00D, "mvpose station")
INPUTS = bytes(range(168))


class Station:
    def __init__(self) -> None:
        self.inputs = INPUTS
        self.outputs: list[bytes] = []


@pytest.fixture
async def served() -> AsyncIterator[tuple[EnipServer, Station]]:
    st = Station()
    srv = EnipServer(ID, lambda: st.inputs, st.outputs.append)
    await srv.start("127.0.0.1", 0, 0)
    yield srv, st
    await srv.stop()


@pytest.fixture
def scanner_ports(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    monkeypatch.setattr(scanner.config, "UDP_IO_MIN_RPI", 4)
    monkeypatch.setattr(scanner.config, "IO_SOCKET_SELECT_TIMEOUT", 0.2)
    yield


def connect() -> tuple[scanner.EtherNetIP, scanner.EtherNetIPExpConnection]:
    """The scanner's session (its calls block: run them off the adapter's loop)."""
    enip = scanner.EtherNetIP("127.0.0.1")
    conn = enip.explicit_conn("127.0.0.1")
    assert conn.registerSession() is not None
    return enip, conn


def disconnect(conn: scanner.EtherNetIPExpConnection) -> None:
    conn.unregisterSession()
    conn.prodsock.close()
    conn.sock.close()


def bits_to_bytes(bits: list[bool]) -> bytes:
    return bytes(sum(1 << i for i in range(8) if bits[8 * k + i]) for k in range(len(bits) // 8))


async def test_pycomm3_reads_and_writes_the_assemblies(served: tuple[EnipServer, Station]
                                                       ) -> None:
    srv, st = served

    def client() -> tuple[object, ...]:
        with CIPDriver(f"127.0.0.1:{srv.port}") as plc:
            ucmm = plc.generic_message(service=0x0E, class_code=4, instance=100, attribute=3,
                                       connected=False)
            routed = plc.generic_message(service=0x0E, class_code=4, instance=150,
                                         attribute=4, connected=False, unconnected_send=True,
                                         route_path="1/0")
            class3 = plc.generic_message(service=0x10, class_code=4, instance=150, attribute=3,
                                         request_data=bytes([3] * 80), connected=True)
            refused = plc.generic_message(service=0x10, class_code=4, instance=100,
                                          attribute=3, request_data=bytes(168), connected=True)
            identity = plc.generic_message(service=0x01, class_code=1, instance=1,
                                           connected=False)
            return ucmm, routed, class3, refused, identity

    ucmm, routed, class3, refused, identity = await asyncio.to_thread(client)
    assert ucmm.error is None and ucmm.value == INPUTS  # type: ignore[attr-defined]
    assert routed.value == struct.pack("<H", 80)  # type: ignore[attr-defined]
    assert class3.error is None  # type: ignore[attr-defined]
    assert st.outputs == [bytes([3] * 80)]
    assert refused.error and "not settable" in refused.error.lower()  # type: ignore[attr-defined]
    assert struct.unpack_from("<HHH", identity.value) == (0xFFFF, 0x2B, 1)  # type: ignore[attr-defined]
    assert any("127.0.0.1" in e and "0x0E" in e for e in srv.stats.last_errors)


async def test_pycomm3_list_identity_over_udp(served: tuple[EnipServer, Station]) -> None:
    srv, _ = served

    def ask() -> bytes:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.settimeout(5)
            s.sendto(struct.pack("<HHII8sI", 0x63, 0, 0, 0, b"abcdefgh", 0),
                     ("127.0.0.1", srv.port))
            return s.recv(1024)

    def discover() -> dict[str, object]:
        return CIPDriver.list_identity(f"127.0.0.1:{srv.port}")  # type: ignore[no-any-return]

    reply = await asyncio.to_thread(ask)
    assert struct.unpack_from("<H", reply) == (0x63,) and b"mvpose station" in reply
    # the identity item's socket address (big-endian) names the encapsulation port in use
    assert struct.unpack_from(">hH", reply, 32) == (2, srv.port)
    ident = await asyncio.to_thread(discover)
    assert ident["product_name"] == "mvpose station" and ident["serial"] == "0badf00d"


async def test_ethernetip_scanner_opens_class1_and_exchanges_io(
        served: tuple[EnipServer, Station], scanner_ports: None,
        monkeypatch: pytest.MonkeyPatch) -> None:
    srv, st = served
    monkeypatch.setattr(scanner, "ENIP_TCP_PORT", srv.port)
    monkeypatch.setattr(scanner, "ENIP_UDP_PORT", srv.io_port)
    enip, conn = await asyncio.to_thread(connect)
    inputs = enip.registerAssembly(scanner.EtherNetIP.ENIP_IO_TYPE_INPUT, 168, 100, conn)
    outputs = enip.registerAssembly(scanner.EtherNetIP.ENIP_IO_TYPE_OUTPUT, 80, 150, conn)
    enip.startIO(udp_port=0)
    try:
        opened = await asyncio.to_thread(
            conn.sendFwdOpenReq, 100, 150, 151, torpi=4, otrpi=4, multiplier=2,
            originator_udp_port=enip.originator_udp_port)
        assert opened == 0
        outputs[0] = outputs[9] = True  # byte 0 = 0x01, byte 1 = 0x02
        conn.produce()
        await until(lambda: bits_to_bytes(inputs) == INPUTS, "the scanner got the inputs")
        await until(lambda: st.outputs and st.outputs[-1][:2] == b"\x01\x02",
                    "the adapter got the outputs")
        st.inputs = bytes(168)
        await until(lambda: bits_to_bytes(inputs) == bytes(168), "new inputs reached it")
        conn.stopProduce()
        assert await asyncio.to_thread(conn.sendFwdCloseReq, 100, 150, 151) == 0
        assert srv.adapter is not None and not srv.adapter.connections
    finally:
        conn.stopProduce()
        enip.stopIO()
        await asyncio.to_thread(disconnect, conn)


async def test_scanner_that_stops_sending_times_out(served: tuple[EnipServer, Station],
                                                    scanner_ports: None,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    srv, _ = served
    monkeypatch.setattr(scanner, "ENIP_TCP_PORT", srv.port)
    monkeypatch.setattr(scanner, "ENIP_UDP_PORT", srv.io_port)
    enip, conn = await asyncio.to_thread(connect)
    enip.registerAssembly(scanner.EtherNetIP.ENIP_IO_TYPE_INPUT, 168, 100, conn)
    enip.registerAssembly(scanner.EtherNetIP.ENIP_IO_TYPE_OUTPUT, 80, 150, conn)
    try:
        # a wrong O→T size first: the scanner is told the size the adapter consumes
        assert await asyncio.to_thread(conn.sendFwdOpenReq, 100, 150, 151, torpi=4, otrpi=4,
                                       outputsz=64) not in (0, None)
        assert await asyncio.to_thread(conn.sendFwdOpenReq, 100, 150, 151, torpi=4, otrpi=4,
                                       multiplier=0) == 0
        conn.produce()
        await until(lambda: srv.stats.images > 0, "outputs arrived")
        conn.stopProduce()  # the scanner dies: no Forward Close
        await until(lambda: srv.stats.timeouts == 1, "the connection timed out")
        assert any("timed out" in e and "127.0.0.1" in e for e in srv.stats.last_errors)
        assert any("O→T size" in e for e in srv.stats.last_errors)
    finally:
        conn.stopProduce()
        await asyncio.to_thread(disconnect, conn)
