"""The S7 poll cycle without sockets: which writes the result block needs, the PDU and block
checks, the DB length probe, the reconnect backoff and the once-per-outage report."""

from __future__ import annotations

import pytest

from drivers.links.s7.poller import (
    Backoff,
    Block,
    BlockError,
    DbWrite,
    Outage,
    ProbeLength,
    ResultWriter,
    check_pdu,
    missing,
    too_short,
)

RESULT = Block("result", 101, 10, 140)
TRIGGER = Block("trigger", 100, 0, 80)
BEAT = slice(2, 4)


def _image(beat: int = 0, code: int = 0) -> bytes:
    img = bytearray(140)
    img[2:4] = beat.to_bytes(2, "big")
    img[20:22] = code.to_bytes(2, "big")
    return bytes(img)


def test_the_first_write_after_a_connection_is_the_whole_block() -> None:
    w = ResultWriter(RESULT, BEAT)
    first = w.next_write(_image())
    assert first == DbWrite(101, 10, _image())
    w.written(first)
    assert w.next_write(_image()) is None  # nothing changed: nothing written
    w.reset()  # a new connection: the PLC's copy is unknown
    assert w.next_write(_image()) == DbWrite(101, 10, _image())


def test_a_moved_heartbeat_alone_writes_only_its_word() -> None:
    w = ResultWriter(RESULT, BEAT)
    w.written(w.next_write(_image(beat=1)) or pytest.fail("no write"))
    beat = w.next_write(_image(beat=2))
    assert beat == DbWrite(101, 12, b"\x00\x02")  # DB byte 10 + 2
    w.written(beat)
    assert w.next_write(_image(beat=2)) is None


def test_any_other_change_writes_the_whole_block_in_one_request() -> None:
    w = ResultWriter(RESULT, BEAT)
    w.written(w.next_write(_image(beat=1)) or pytest.fail("no write"))
    whole = w.next_write(_image(beat=2, code=7))
    assert whole == DbWrite(101, 10, _image(beat=2, code=7))


def test_a_write_that_was_not_acknowledged_is_written_again() -> None:
    w = ResultWriter(RESULT, BEAT)
    w.written(w.next_write(_image()) or pytest.fail("no write"))
    lost = w.next_write(_image(code=3))
    assert lost is not None  # ... and the connection dropped before the PLC answered
    assert w.next_write(_image(code=3)) == lost


def test_an_image_of_the_wrong_size_is_refused() -> None:
    with pytest.raises(ValueError, match="139 bytes"):
        ResultWriter(RESULT, BEAT).next_write(bytes(139))


def test_the_pdu_must_hold_the_result_block_in_one_write() -> None:
    check_pdu(240, TRIGGER, RESULT, "plc")  # the smallest PDU of an S7 CPU
    check_pdu(175, TRIGGER, RESULT, "plc")
    with pytest.raises(BlockError) as err:
        check_pdu(174, TRIGGER, RESULT, "10.0.0.5:102")
    text = str(err.value)
    for part in ("10.0.0.5:102", "174 bytes", "DB101.DBB10..149", "140 bytes", "175"):
        assert part in text, text


def test_block_errors_name_the_plc_the_db_its_length_and_the_need() -> None:
    text = str(too_short(RESULT, 64, "10.0.0.5:102"))
    for part in ("10.0.0.5:102", "DB101", "64 bytes long", "10..149", "150 bytes"):
        assert part in text, text
    text = str(missing(TRIGGER, "10.0.0.5:102"))
    for part in ("no DB100", "Optimized block access", "0..79"):
        assert part in text, text


@pytest.mark.parametrize("length", [0, 1, 2, 63, 64, 79, 149])
def test_the_probe_finds_a_dbs_length_with_one_byte_reads(length: int) -> None:
    probe = ProbeLength(150)
    reads = 0
    while not probe.done:
        probe.answer(probe.next_offset < length)
        reads += 1
    assert probe.length == length
    assert reads <= 8  # log2(150)


def test_the_backoff_doubles_up_to_its_limit_and_starts_again_after_a_success() -> None:
    b = Backoff(0.1, 0.5)
    assert [b.next() for _ in range(5)] == [0.1, 0.2, 0.4, 0.5, 0.5]
    b.reset()
    assert b.next() == 0.1


def test_an_outage_is_news_once_and_again_when_its_kind_changes() -> None:
    o = Outage()
    assert o.lost("refused") is True
    assert [o.lost(why) for why in ("refused", "reset", "timed out")] == [False] * 3
    assert o.reason == "timed out"
    assert o.lost("DB101 is 64 bytes long", "block") is True  # now it answers, but does not fit
    assert o.lost("DB101 is 64 bytes long", "block") is False
    assert o.outages == 1 and not o.up
    assert o.connected() is True  # the end of a reported outage is worth a line
    assert o.up and o.connected() is False
    assert o.lost("dropped") is True and o.outages == 2


def test_the_station_files_s7_block_is_checked_field_by_field() -> None:
    from drivers.links import LinkSettingsError, link_settings

    cfg = link_settings({"s7": {"host": "10.1.2.7"}})["s7"]
    assert cfg.tsaps == (0x0100, 0x0101)  # type: ignore[attr-defined]  # rack 0, slot 1
    cfg = link_settings({"s7": {"host": "10.1.2.7", "rack": 0, "slot": 2}})["s7"]
    assert cfg.tsaps == (0x0100, 0x0102)  # type: ignore[attr-defined]  # an S7-300
    cfg = link_settings({"s7": {"host": "h", "local_tsap": 0x1000, "remote_tsap": 0x2001}})["s7"]
    assert cfg.tsaps == (0x1000, 0x2001)  # type: ignore[attr-defined]
    bad = [
        ({"host": "h", "allowlist": ["10.0.0.0/8"]}, "links.s7.allowlist", "Extra inputs"),
        ({}, "links.s7.host", "Field required"),
        ({"host": "h", "remote_tsap": 0x0102}, "links.s7", "go together"),
        ({"host": "h", "slot": 2, "local_tsap": 1, "remote_tsap": 2}, "links.s7", "not both"),
        ({"host": "h", "result_db": 100, "result_start": 40}, "links.s7", "overlaps"),
        ({"host": "h", "poll_s": 0}, "links.s7.poll_s", "greater than or equal"),
        ({"host": "h", "reconnect_min_s": 2, "reconnect_max_s": 1}, "links.s7", "below"),
    ]
    for block, where, what in bad:
        with pytest.raises(LinkSettingsError) as err:
            link_settings({"s7": block})
        assert any(w == where and what in m for w, m, _ in err.value.problems), err.value
    same_db = link_settings({"s7": {"host": "h", "result_db": 100, "result_start": 80}})
    assert same_db["s7"].result_db == 100  # type: ignore[attr-defined]  # no overlap: fine
