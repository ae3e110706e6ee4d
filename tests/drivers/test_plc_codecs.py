"""Register codecs against fixed byte patterns and two independent Modbus libraries."""

from __future__ import annotations

from typing import Literal

import numpy as np
import pytest
from pymodbus.client import AsyncModbusTcpClient
from pyModbusTCP import utils as mtcp

from drivers.links import codecs as c
from drivers.links.modbus import HandshakeConfig, WordOrder
from mvpose_core.transforms import (
    RobotConvention,
    from_robot,
    make_transform,
    rotvec_to_matrix,
    to_robot,
    transform_error,
)

ORDERS = [WordOrder.ABCD, WordOrder.CDAB]


def test_known_byte_patterns() -> None:
    # 123.45 = 0x42F6E666 (IEEE 754 single), the test register a PLC programmer checks.
    assert c.encode_float32(123.45, WordOrder.ABCD) == [0x42F6, 0xE666]
    assert c.encode_float32(123.45, WordOrder.CDAB) == [0xE666, 0x42F6]
    assert c.encode_int32(-2, WordOrder.ABCD) == [0xFFFF, 0xFFFE]
    assert c.encode_int32(0x12345678, WordOrder.CDAB) == [0x5678, 0x1234]
    assert c.encode_uint32(0xDEADBEEF, WordOrder.ABCD) == [0xDEAD, 0xBEEF]
    assert c.decode_int32([0x8000, 0x0000], WordOrder.ABCD) == -(2**31)


@pytest.mark.parametrize("order", ORDERS)
def test_int_and_float_agree_with_pymodbus_and_pymodbustcp(order: WordOrder) -> None:
    rng = np.random.default_rng(7)
    word: Literal["big", "little"] = "big" if order is WordOrder.ABCD else "little"
    big = order is WordOrder.ABCD
    dt = AsyncModbusTcpClient.DATATYPE
    for v in rng.integers(-(2**31), 2**31, size=200):
        regs = c.encode_int32(int(v), order)
        assert regs == AsyncModbusTcpClient.convert_to_registers(int(v), dt.INT32, word_order=word)
        assert mtcp.get_2comp(mtcp.word_list_to_long(regs, big_endian=big)[0], 32) == v
        assert c.decode_int32(regs, order) == v
    for f in rng.normal(0, 1e3, size=200).astype(np.float32):
        regs = c.encode_float32(float(f), order)
        assert regs == AsyncModbusTcpClient.convert_to_registers(
            float(f), dt.FLOAT32, word_order=word
        )
        assert mtcp.decode_ieee(mtcp.word_list_to_long(regs, big_endian=big)[0]) == float(f)
        assert c.decode_float32(regs, order) == float(f)


def test_range_errors_name_the_value() -> None:
    with pytest.raises(ValueError, match="2147483648"):
        c.encode_int32(2**31, WordOrder.ABCD)
    with pytest.raises(ValueError, match="-1"):
        c.encode_uint32(-1, WordOrder.ABCD)
    with pytest.raises(ValueError, match=r"got 3: \[1, 2, 3\]"):
        c.decode_int32([1, 2, 3], WordOrder.ABCD)


def test_ascii_round_trip_and_limits() -> None:
    regs = c.encode_ascii("WVWZZZ1KZ8W000123", 20)
    assert len(regs) == 20
    assert regs[0] == ord("W") << 8 | ord("V")
    assert c.decode_ascii(regs) == "WVWZZZ1KZ8W000123"
    assert c.decode_ascii(c.encode_ascii("", 20)) == ""
    with pytest.raises(ValueError, match="41 characters"):
        c.encode_ascii("x" * 41, 20)
    assert c.decode_ascii([0xC3A9, 0x4100]) == "??A"  # non-ASCII bytes never raise


def test_pose_scales_per_convention() -> None:
    fanuc = c.encode_pose_int((1.0, -2.0, 0.5, 1.0, 0.0, -0.0001), "fanuc", WordOrder.ABCD)
    counts = [c.decode_int32(fanuc[i : i + 2], WordOrder.ABCD) for i in range(0, 12, 2)]
    assert counts == [1000, -2000, 500, 10000, 0, -1]
    ur = c.encode_pose_int((0.001, 0, 0, 0.5, 0, 0), "ur", WordOrder.ABCD)
    assert c.decode_int32(ur[0:2], WordOrder.ABCD) == 1000  # 1 mm as µm
    assert c.decode_int32(ur[6:8], WordOrder.ABCD) == 500000  # 0.5 rad as µrad
    assert c.fits_int32((2.2e6, 0, 0, 0, 0, 0), "fanuc") is False  # 2.2 km in µm overflows
    assert c.fits_int32((2.1e6, 0, 0, 0, 0, 0), "fanuc") is True
    assert c.fits_int32((float("nan"), 0, 0, 0, 0, 0), "fanuc") is False


@pytest.mark.parametrize("conv", list(RobotConvention))
def test_pose_to_plc_round_trips_every_convention(conv: RobotConvention) -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        T = make_transform(rotvec_to_matrix(rng.normal(0, 0.3, 3)), rng.normal(0, 20, 3))
        plc = c.pose_to_plc(to_robot(T, conv), conv)
        assert len(plc) == 6
        back = from_robot(c.plc_to_pose(plc, conv), conv)
        deg, mm = transform_error(back, T)
        assert deg < 1e-9 and mm < 1e-9
        # Through the int32 block the resolution is the documented count size.
        regs = c.encode_pose_int(plc, conv, WordOrder.CDAB)
        via_int = from_robot(
            c.plc_to_pose(c.decode_pose_int(regs, conv, WordOrder.CDAB), conv), conv
        )
        deg, mm = transform_error(via_int, T)
        assert deg < 2e-4 and mm < 2e-3


def test_abb_quaternion_with_negative_scalar_is_flipped() -> None:
    q = np.array([-0.9, 0.1, -0.3, 0.2])
    q /= np.linalg.norm(q)
    plc = c.pose_to_plc((1, 2, 3, *q), "abb")
    assert np.allclose(plc[3:], -q[1:])
    full = c.plc_to_pose(plc, "abb")
    assert np.allclose(full[3:], -q)
    with pytest.raises(ValueError, match="norm"):
        c.plc_to_pose((0, 0, 0, 0.9, 0.9, 0), "abb")


def test_convention_codes() -> None:
    for conv in RobotConvention:
        assert c.convention_from_code(conv.code) is conv
    with pytest.raises(ValueError, match="code 9"):
        c.convention_from_code(9)


def test_config_validation_and_allowlist() -> None:
    with pytest.raises(ValueError, match="watchdog_s.*-1"):
        HandshakeConfig(watchdog_s=-1)
    with pytest.raises(ValueError, match="'plc-1'"):
        HandshakeConfig(allowlist=("plc-1",))
    cfg = HandshakeConfig(allowlist=("10.1.2.0/24", "192.168.0.7"))
    assert cfg.allows("10.1.2.99") and cfg.allows("192.168.0.7")
    assert cfg.allows("::ffff:10.1.2.3")  # IPv4-mapped IPv6 peer of a dual-stack socket
    assert not cfg.allows("10.1.3.1") and not cfg.allows("127.0.0.1") and not cfg.allows("")
    assert HandshakeConfig().allows("203.0.113.5")  # empty allowlist: anyone
