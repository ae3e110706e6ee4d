"""The EtherNet/IP link with the handshake: the PLC twin over class 1 I/O (its EtherNet/IP port)
against :class:`~drivers.links.enip.EnipLink` with the arithmetic pipeline; what the station
shows when the scanner stops or goes idle; the shipped EDS."""

from __future__ import annotations

import asyncio
import struct
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from plc_peers import ArithmeticHandler
from test_plc_server import check_result

import drivers.links.enip as enip_pkg
from drivers.links import layout as r
from drivers.links import link_settings
from drivers.links.enip import EnipLink
from drivers.links.enip.codec import IoFrame
from drivers.links.enip.eds import eds_text, main
from drivers.links.enip.settings import EnipLinkConfig
from drivers.links.enip.twin import EnipPort, EnipPortError, enip_twin
from drivers.links.layout import ErrorCode, State
from drivers.links.twin import PlcTwin
from tests.waiting import until


def config(**kw: object) -> EnipLinkConfig:
    return EnipLinkConfig.model_validate({"port": 0, "io_port": 0, "watchdog_s": 10.0, **kw})


@pytest.fixture
async def link() -> AsyncIterator[tuple[EnipLink, ArithmeticHandler]]:
    handler = ArithmeticHandler()
    handler.recipe = 1
    lk = EnipLink(config(watchdog_s=0.3), handler)  # type: ignore[arg-type]
    await lk.start()
    yield lk, handler
    await lk.stop()


async def attached(lk: EnipLink, rpi_ms: float = 4.0, multiplier: int = 7) -> PlcTwin:
    twin = await enip_twin("127.0.0.1", lk.port, rpi_ms=rpi_ms, multiplier=multiplier).connect()
    await twin.enable()
    return twin


async def test_triggers_over_class1_io(link: tuple[EnipLink, ArithmeticHandler]) -> None:
    lk, handler = link
    twin = await attached(lk)
    beat = asyncio.create_task(twin.keep_alive(0.05))
    try:
        status = await twin.read_status()
        assert status.state is State.READY and status.recipe == 1
        # CIP is little-endian: the test values decode with the CDAB word order the port says
        assert status.test_float == pytest.approx(r.TEST_FLOAT, abs=1e-5)
        assert status.test_int == r.TEST_INT
        for n, tid in enumerate([7, 26, 0xFFFF_FFFE], start=1):
            answer = await twin.cycle(tid, part_id=f"VIN{tid}", timeout=10.0)
            check_result(answer, tid)
            assert answer.result_id == n
        assert [q.part_id for q in handler.requests] == ["VIN7", "VIN26", f"VIN{0xFFFF_FFFE}"]
        st = lk.status()
        assert st["running"] and st["plc_online"] and len(st["io_connections"]) == 1
        assert lk.line_state() == "READY"
    finally:
        twin.stop_keep_alive()
        await beat
        twin.close()
    await until(lambda: not lk.status()["io_connections"], "the Forward Close")


async def test_a_scanner_that_stops_is_reported_as_a_lost_plc(
        link: tuple[EnipLink, ArithmeticHandler]) -> None:
    lk, handler = link
    twin = await attached(lk, rpi_ms=10.0, multiplier=5)
    check_result(await twin.cycle(3, timeout=10.0), 3)
    twin.abort()  # no Forward Close: the connection times out (10 ms × 128)
    await until(lambda: lk.server is not None and lk.server.stats.timeouts >= 1,
                "the connection timed out")
    await until(lambda: lk.line_state() == "ERROR", "the watchdog")
    assert lk.runner is not None and lk.runner.machine.error is ErrorCode.WATCHDOG
    assert not lk.status()["plc_online"]
    assert any("timed out" in e and "127.0.0.1" in e for e in lk.status()["last_errors"])
    # a new connection and the PLC's error reset bring it back
    twin = await attached(lk)
    try:
        await twin.reset_error()
        check_result(await twin.cycle(4, timeout=10.0), 4)
        assert handler.resets >= 1
    finally:
        twin.close()


async def test_idle_header_clears_the_outputs(link: tuple[EnipLink, ArithmeticHandler]) -> None:
    lk, _ = link
    port = EnipPort("127.0.0.1", lk.port)
    twin = PlcTwin(port)
    await twin.connect()
    try:
        await twin.enable()
        await twin.wait_for(lambda s: s.state is State.READY, 5.0, "READY")
        # the scanner goes to program mode: the run/idle header says idle
        assert port._udp is not None and lk.server is not None
        port._producer.cancel()  # type: ignore[union-attr]
        idle = IoFrame(port._o_t_id, 99_999, 99, struct.pack("<I", 0) + bytes(80))
        port._udp.sendto(idle.pack(), port._dest)
        await until(lambda: lk.line_state() == "HALTED", "HALTED after idle")
        assert lk.server.adapter is not None and lk.server.adapter.outputs == bytes(80)
    finally:
        twin.close()


async def test_wrong_rpi_is_refused_with_its_code() -> None:
    handler = ArithmeticHandler()
    lk = EnipLink(config(min_rpi_ms=8.0), handler)  # type: ignore[arg-type]
    await lk.start()
    try:
        with pytest.raises(EnipPortError, match="0x0111"):
            await EnipPort("127.0.0.1", lk.port, rpi_ms=4.0).connect()
        assert handler.requests == [] and lk.status()["refused"] == 1
    finally:
        await lk.stop()


def test_settings_forbid_unknown_keys_and_name_the_field() -> None:
    with pytest.raises(ValueError, match=r"links\.enip\.rpi"):
        link_settings({"enip": {"rpi": 4}})
    with pytest.raises(ValueError, match=r"links\.enip\.min_rpi_ms"):
        link_settings({"enip": {"min_rpi_ms": 1.0}})
    assert isinstance(link_settings({"enip": {}})["enip"], EnipLinkConfig)


def test_the_shipped_eds_is_the_generated_one(capsys: pytest.CaptureFixture[str]) -> None:
    shipped = Path(enip_pkg.__file__).with_name("mvpose.eds").read_text()
    assert shipped == eds_text(config().identity(), config().assemblies())
    assert main([]) == 0 and capsys.readouterr().out == shipped
    assert "Assem100" in shipped and f"\n                {r.INPUT_SIZE}," in shipped
    assert '"20 04 24 97 2C 96 2C 64"' in shipped
    # every field of the layout is a parameter, in order
    for f in (*r.INPUT_FIELDS, *r.OUTPUT_FIELDS):
        assert f'"{f.name}"' in shipped


async def test_bad_input_gets_its_status_a_log_line_and_nothing_else(
        link: tuple[EnipLink, ArithmeticHandler], caplog: pytest.LogCaptureFixture) -> None:
    lk, handler = link
    reader, writer = await asyncio.open_connection("127.0.0.1", lk.port)

    async def ask(raw: bytes) -> bytes:
        writer.write(raw)
        head = await asyncio.wait_for(reader.readexactly(24), 10)
        return head + await reader.readexactly(int.from_bytes(head[2:4], "little"))

    def encap(command: int, data: bytes = b"", session: int = 0) -> bytes:
        return struct.pack("<HHII8sI", command, len(data), session, 0, b"badinput", 0) + data

    try:
        assert struct.unpack_from("<I", await ask(encap(0x99)), 8) == (0x01,)  # unknown command
        reply = await ask(encap(0x6F, bytes(8), session=0x1234))  # no session registered
        assert struct.unpack_from("<I", reply, 8) == (0x64,)
        reply = await ask(encap(0x65, b"\x01\x00\x00\x00"))
        session = struct.unpack_from("<I", reply, 4)[0]
        # Set_Attribute_Single on the input assembly: CIP 0x0E in the reply's general status
        mr = b"\x10\x03\x20\x04\x24\x64\x30\x03" + bytes(168)
        cpf = struct.pack("<IHHHHHH", 0, 0, 2, 0, 0, 0xB2, len(mr)) + mr
        reply = await ask(encap(0x6F, cpf, session))
        assert struct.unpack_from("<I", reply, 8) == (0,) and reply[24 + 16 + 2] == 0x0E
        # a Forward Open for 64 output bytes: CIP 0x01, extended 0x0127 and the size wanted
        fo = struct.pack("<BBIIHHIB3sIHIHBB", 0x0A, 0xF0, 0, 1, 9, 1, 2, 5, bytes(3), 4000,
                         64 | 0x4800, 4000, 170 | 0x4800, 0x11, 4) \
            + b"\x20\x04\x24\x97\x2c\x96\x2c\x64"
        mr = b"\x54\x02\x20\x06\x24\x01" + fo
        cpf = struct.pack("<IHHHHHH", 0, 0, 2, 0, 0, 0xB2, len(mr)) + mr
        reply = await ask(encap(0x6F, cpf, session))
        body = reply[24 + 16:]
        assert body[2] == 0x01 and struct.unpack_from("<HH", body, 4) == (0x0127, 86)
        # a length past the limit: status 0x0065, and the connection is closed
        writer.write(struct.pack("<HHII8sI", 0x6F, 60000, session, 0, b"badinput", 0))
        head = await asyncio.wait_for(reader.readexactly(24), 10)
        assert struct.unpack_from("<I", head, 8) == (0x65,)
        assert await asyncio.wait_for(reader.read(10), 10) == b""
    finally:
        writer.close()
    assert handler.requests == [] and lk.runner is not None
    assert lk.runner.machine.stats.triggers == 0
    refused = [r.getMessage() for r in caplog.records if "EtherNet/IP" in r.getMessage()]
    assert len(refused) >= 5 and all("127.0.0.1" in m for m in refused), refused
    twin = await attached(lk)  # the adapter serves on
    try:
        check_result(await twin.cycle(5, timeout=10.0), 5)
    finally:
        twin.close()


async def test_a_plc_with_msg_instructions_only_triggers_through_the_assemblies() -> None:
    """pycomm3 as a PLC without class 1 I/O: Set_Attribute_Single on the output assembly, Get on
    the input assembly (CIP's byte order: the layout's words and 32-bit values little-endian)."""
    from pycomm3 import CIPDriver

    handler = ArithmeticHandler()
    handler.recipe = 1
    lk = EnipLink(config(), handler)  # type: ignore[arg-type]
    await lk.start()

    def plc() -> tuple[int, int, int]:
        with CIPDriver(f"127.0.0.1:{lk.port}") as drv:
            def put(control: int, beat: int, trigger_id: int = 0, part: bytes = b"") -> None:
                out = bytearray(r.OUTPUT_SIZE)
                struct.pack_into("<HH", out, 0, control, beat)
                struct.pack_into("<I", out, 2 * r.HR_TRIGGER_ID, trigger_id)
                out[2 * r.HR_PART_ID : 2 * r.HR_PART_ID + len(part)] = part
                done = drv.generic_message(service=0x10, class_code=4, instance=150,
                                           attribute=3, request_data=bytes(out))
                assert done.error is None, done.error

            def get() -> bytes:
                got = drv.generic_message(service=0x0E, class_code=4, instance=100, attribute=3)
                assert got.error is None and len(got.value) == r.INPUT_SIZE, got
                return bytes(got.value)

            def wait(bit: int) -> bytes:
                for _ in range(2000):
                    image = get()
                    if struct.unpack_from("<H", image)[0] & bit:
                        return image
                raise AssertionError(f"status bit {bit:#x} never came")

            en = int(r.Control.TRIGGER_ENABLE)
            put(en, 1)
            wait(int(r.Status.READY))
            put(en | int(r.Control.TRIGGER), 2, 42, b"MSG-42")
            image = wait(int(r.Status.RESULT_VALID))
            put(en | int(r.Control.RESULT_ACK), 3)
            echo, result_id = struct.unpack_from("<II", image, 2 * r.IR_TRIGGER_ID)
            (code,) = struct.unpack_from("<H", image, 2 * r.IR_RESULT_CODE)
            return echo, result_id, code

    try:
        echo, result_id, code = await asyncio.to_thread(plc)
    finally:
        await lk.stop()
    assert (echo, result_id, code) == (42, 1, 0)
    assert [(q.trigger_id, q.part_id) for q in handler.requests] == [(42, "MSG-42")]
