"""The handshake state machine on its own: register writes and clock values in, image out."""

from __future__ import annotations

import math

import pytest

from drivers.links import codecs as c
from drivers.links import layout as r
from drivers.links.base import HandEyeOutcome, LinkOutcome, VerifyOutcome
from drivers.links.handshake import Handshake, HandshakeConfig, Measure, ResetPipeline, RunCommand
from drivers.links.layout import (
    Command,
    Control,
    ErrorCode,
    State,
    Status,
    VerifyVerdict,
    WordOrder,
)
from mvpose_core.reasons import Reason

EN = Control.TRIGGER_ENABLE


def answer(code: int = 0, offset: tuple[float, ...] | None = None, result_id: int = 1,
           **kw: float) -> LinkOutcome:
    """The station's answer: a record's seq (result_id) and the offset in the recipe's
    convention (None unless OK)."""
    return LinkOutcome(code, result_id, offset, **kw)  # type: ignore[arg-type]


class Plc:
    """Drives a Handshake the way the PLC program writes registers, with an explicit clock."""

    def __init__(self, order: WordOrder = WordOrder.ABCD, **cfg: float) -> None:
        self.order = order
        self.m = Handshake(HandshakeConfig(word_order=order, **cfg), convention_code=1, now=0.0)
        self.beat = 0
        self.t = 0.0

    def ctl(self, control: Control | int, dt: float = 0.01, beat: bool = True) -> list:
        self.t += dt
        self.beat += beat
        return self.m.write(r.HR_CONTROL, [int(control), self.beat], self.t)

    def status(self) -> Status:
        return Status(self.m.image[r.IR_STATUS])

    def u32(self, address: int) -> int:
        return c.decode_uint32(self.m.image[address : address + 2], self.order)

    def ready(self) -> Plc:
        self.ctl(EN)
        self.m.set_recipe(1)
        return self

    def trigger(self, trigger_id: int, view: int = 0, extra: int = 0) -> list:
        self.m.write(r.HR_TRIGGER_ID, [*c.encode_uint32(trigger_id, self.order), view], self.t)
        return self.ctl(EN | Control.TRIGGER | extra)


def test_states_from_start_to_ready() -> None:
    p = Plc()
    assert p.m.state is State.PREOPERATIONAL and not p.status() & Status.ONLINE
    p.ctl(0)
    assert p.m.state is State.HALTED and p.status() & Status.ONLINE
    p.ctl(EN)
    assert p.m.state is State.INITIALIZED and not p.status() & Status.READY
    p.m.set_recipe(4)
    assert p.m.state is State.READY and p.status() & Status.READY
    assert p.m.image[r.IR_STATE] == State.READY and p.m.image[r.IR_RECIPE] == 4


@pytest.mark.parametrize("order", [WordOrder.ABCD, WordOrder.CDAB])
def test_trigger_result_ack_cycle(order: WordOrder) -> None:
    p = Plc(order).ready()
    pose = c.encode_pose_int((100.0, -20.5, 3.0, 0.5, -1.25, 179.9), "fanuc", order)
    p.m.write(r.HR_ROBOT_POSE, pose, p.t)
    p.m.write(r.HR_PART_ID, c.encode_ascii("VIN42", 20), p.t)
    effects = p.trigger(0x0102_0304, view=2, extra=Control.ROBOT_POSE_VALID)
    assert len(effects) == 1 and isinstance(effects[0], Measure)
    req = effects[0].request
    assert (req.trigger_id, req.view_index, req.part_id, req.recipe) == (0x01020304, 2, "VIN42", 1)
    assert req.robot_pose is not None
    assert all(
        math.isclose(a, b)
        for a, b in zip(req.robot_pose, (100, -20.5, 3, 0.5, -1.25, 179.9), strict=True)
    )
    s = p.status()
    assert s & Status.TRIGGER_ACK and s & Status.BUSY and not s & Status.READY
    assert p.m.state is State.SINGLE_EXECUTION and p.u32(r.IR_TRIGGER_ID) == 0x01020304
    toggle = s & Status.DONE_TOGGLE

    p.m.measured(LinkOutcome(0, 1, (1.0, 2.0, 3.0, 0.1, 0.2, 0.3), 0.05, 0.01, 12.34, 1))
    s = p.status()
    assert s & Status.RESULT_VALID and s & Status.RESULT_OK and (s & Status.DONE_TOGGLE) != toggle
    assert not s & Status.READY  # not before the acknowledgement
    assert p.u32(r.IR_RESULT_ID) == 1 and p.m.image[r.IR_PROCESSING_TIME] == 123
    ints = c.decode_pose_int(p.m.image[r.IR_OFFSET_INT : r.IR_OFFSET_INT + 12], "fanuc", order)
    assert ints == (1.0, 2.0, 3.0, 0.1, 0.2, 0.3)
    assert c.decode_int32(p.m.image[r.IR_SIGMA_TRANS : r.IR_SIGMA_TRANS + 2], order) == 50

    p.ctl(EN | Control.RESULT_ACK)  # trigger released and result acknowledged together
    s = p.status()
    assert not s & (Status.RESULT_VALID | Status.TRIGGER_ACK) and s & Status.READY
    assert p.u32(r.IR_RESULT_ID) == 1  # the data stays readable after the acknowledgement


def test_ack_is_an_edge_so_a_held_ack_never_swallows_the_next_result() -> None:
    p = Plc().ready()
    p.trigger(1)
    p.m.measured(answer())
    p.ctl(EN | Control.RESULT_ACK)
    p.m.write(r.HR_TRIGGER_ID, c.encode_uint32(2, WordOrder.ABCD), p.t)
    assert p.ctl(EN | Control.RESULT_ACK | Control.TRIGGER)  # ACK still high: trigger accepted
    p.m.measured(answer(result_id=2))
    p.ctl(EN | Control.RESULT_ACK)
    assert p.status() & Status.RESULT_VALID and p.u32(r.IR_RESULT_ID) == 2


def test_trigger_while_busy_is_missed_and_gives_no_second_result() -> None:
    p = Plc().ready()
    assert p.trigger(1)
    p.ctl(EN)
    assert p.trigger(2) == []
    assert p.status() & Status.MISSED_TRIGGER and p.m.stats.missed_triggers == 1
    assert p.u32(r.IR_TRIGGER_ID) == 1
    p.m.measured(answer())
    assert p.u32(r.IR_RESULT_ID) == 1
    p.ctl(EN | Control.RESULT_ACK)
    assert p.trigger(3)  # the next accepted trigger clears MISSED_TRIGGER
    assert not p.status() & Status.MISSED_TRIGGER


def test_unacknowledged_result_blocks_the_next_trigger() -> None:
    p = Plc().ready()
    p.trigger(1)
    p.m.measured(answer())
    p.ctl(EN)
    assert p.trigger(2) == [] and p.status() & Status.MISSED_TRIGGER
    assert p.u32(r.IR_RESULT_ID) == 1 and p.status() & Status.RESULT_VALID


def test_intermediate_view_gives_view_done_not_a_result() -> None:
    p = Plc().ready()
    p.trigger(10, view=1)
    p.m.measured(answer(result_id=0, views_done=1, final=False))
    s = p.status()
    assert s & Status.VIEW_DONE and not s & Status.RESULT_VALID and p.u32(r.IR_RESULT_ID) == 0
    assert p.m.image[r.IR_VIEWS_DONE] == 1
    p.ctl(EN | Control.RESULT_ACK)
    p.trigger(11, view=2)
    p.m.measured(answer(views_done=2))
    assert p.status() & Status.RESULT_VALID and p.u32(r.IR_RESULT_ID) == 1
    assert p.m.stats.views == 1 and p.m.stats.results == 1


def test_watchdog_trips_and_needs_heartbeat_and_reset() -> None:
    p = Plc(watchdog_s=0.5).ready()
    p.m.tick(p.t + 0.4)
    assert p.m.state is State.READY
    p.m.tick(p.t + 0.6)
    assert p.m.state is State.ERROR and p.m.error is ErrorCode.WATCHDOG
    assert not p.status() & (Status.ONLINE | Status.READY) and p.status() & Status.ERROR
    p.t += 1.0
    assert p.ctl(EN | Control.ERROR_RESET, beat=False) == []  # still no heartbeat: stays
    assert p.m.state is State.ERROR
    p.ctl(EN)
    effects = p.ctl(EN | Control.ERROR_RESET)
    assert effects == [ResetPipeline()] and p.m.state is State.READY
    assert p.m.stats.watchdog_trips == 1


def test_held_trigger_forces_reset_and_still_delivers_the_result() -> None:
    p = Plc(trigger_hold_s=0.3).ready()
    p.trigger(5)
    p.m.measured(answer())
    p.m.tick(p.t + 0.2)
    assert p.status() & Status.TRIGGER_ACK
    p.m.tick(p.t + 0.4)
    assert p.m.error is ErrorCode.TRIGGER_HELD and not p.status() & Status.TRIGGER_ACK
    assert p.status() & Status.RESULT_VALID and p.u32(r.IR_RESULT_ID) == 1
    p.ctl(EN | Control.TRIGGER | Control.ERROR_RESET)
    assert p.m.state is State.ERROR  # reset refused while the trigger is still held
    p.ctl(EN | Control.RESULT_ACK)
    assert p.ctl(EN | Control.ERROR_RESET) == [ResetPipeline()]
    assert p.m.state is State.READY and p.m.stats.held_triggers == 1


def test_commands() -> None:
    p = Plc().ready()
    p.m.write(r.HR_COMMAND, [Command.SELECT_RECIPE, 7], p.t)
    (effect,) = p.ctl(EN | Control.EXECUTE_COMMAND)
    assert effect == RunCommand(Command.SELECT_RECIPE, 7)
    assert p.status() & Status.COMMAND_BUSY and not p.status() & Status.READY
    p.m.command_done(Command.SELECT_RECIPE, 7, 0)
    assert p.status() & Status.COMMAND_DONE and p.m.image[r.IR_RECIPE] == 7
    p.ctl(EN)
    assert not p.status() & Status.COMMAND_DONE and p.status() & Status.READY

    p.m.write(r.HR_COMMAND, [99, 0], p.t)
    assert p.ctl(EN | Control.EXECUTE_COMMAND) == []
    assert p.status() & Status.COMMAND_FAILED
    assert p.m.image[r.IR_COMMAND_RESULT] == Reason.UNKNOWN_COMMAND
    p.ctl(EN)
    p.m.write(r.HR_COMMAND, [Command.SELECT_RECIPE, 0], p.t)
    p.ctl(EN | Control.EXECUTE_COMMAND)
    assert p.m.image[r.IR_COMMAND_RESULT] == Reason.BAD_ARGUMENT
    p.ctl(EN)
    p.m.write(r.HR_COMMAND, [Command.TEACH_REFERENCE, 0], p.t)
    p.ctl(EN | Control.EXECUTE_COMMAND)
    p.m.command_done(Command.TEACH_REFERENCE, 0, 12)
    assert p.status() & Status.COMMAND_FAILED and p.m.image[r.IR_COMMAND_RESULT] == 12


@pytest.mark.parametrize("order", [WordOrder.ABCD, WordOrder.CDAB])
def test_verify_publishes_its_block_before_the_command_ends(order: WordOrder) -> None:
    p = Plc(order).ready()
    verify = VerifyOutcome(0, 41, passed=False, difference=(0.3, -0.4, 0.0, 0.01, 0.0, -0.02),
                           displacement_mm=0.5, rotation_deg=0.022, limit_mm=0.2,
                           limit_deg=0.1)
    p.m.write(r.HR_COMMAND, [Command.VERIFY, 0], p.t)
    (effect,) = p.ctl(EN | Control.EXECUTE_COMMAND)
    assert effect == RunCommand(Command.VERIFY, 0)
    p.m.verified(verify)
    p.m.command_done(Command.VERIFY, 0, verify.result_code)
    img = p.m.image
    assert p.status() & Status.COMMAND_DONE and img[r.IR_COMMAND_RESULT] == 0
    assert p.u32(r.IR_VERIFY_RESULT_ID) == 41
    assert img[r.IR_VERIFY_VERDICT] == VerifyVerdict.FAILED
    diff = c.decode_pose_float(img[r.IR_VERIFY_DIFFERENCE : r.IR_VERIFY_DIFFERENCE + 12], order)
    assert diff == pytest.approx(verify.difference, abs=1e-6)
    assert c.decode_float32(img[r.IR_VERIFY_DISPLACEMENT : r.IR_VERIFY_DISPLACEMENT + 2],
                            order) == pytest.approx(0.5)
    assert c.decode_float32(img[r.IR_VERIFY_ROTATION : r.IR_VERIFY_ROTATION + 2],
                            order) == pytest.approx(0.022)

    # the next verify clears the verdict at its start; one without a verdict leaves it NONE,
    # names its record and publishes zeros, and the command fails with the reason
    p.ctl(EN)
    p.ctl(EN | Control.EXECUTE_COMMAND)
    assert img[r.IR_VERIFY_VERDICT] == VerifyVerdict.NONE
    p.m.verified(VerifyOutcome(int(Reason.MARKS_MISSING), 42, message="no marks"))
    p.m.command_done(Command.VERIFY, 0, Reason.MARKS_MISSING)
    assert p.status() & Status.COMMAND_FAILED
    assert img[r.IR_COMMAND_RESULT] == Reason.MARKS_MISSING
    assert p.u32(r.IR_VERIFY_RESULT_ID) == 42 and img[r.IR_VERIFY_VERDICT] == 0
    assert img[r.IR_VERIFY_DIFFERENCE : r.IR_HANDEYE_POSES] == [0] * 16


@pytest.mark.parametrize("order", [WordOrder.ABCD, WordOrder.CDAB])
def test_handeye_add_pose_reads_the_pose_as_a_trigger_does(order: WordOrder) -> None:
    p = Plc(order).ready()
    pose = (1210.5, -302.125, 905.75, 175.0, -20.0, 10.0)
    p.m.write(r.HR_ROBOT_POSE, c.encode_pose_int(pose, "fanuc", order), p.t)
    p.m.write(r.HR_COMMAND, [Command.HANDEYE_ADD_POSE, 0], p.t)
    (effect,) = p.ctl(EN | Control.EXECUTE_COMMAND | Control.ROBOT_POSE_VALID)
    assert effect.command is Command.HANDEYE_ADD_POSE and effect.refused is None
    assert effect.robot_pose == pytest.approx(pose, abs=1e-6)
    out = HandEyeOutcome(205, poses=7, pose=8, message="board not found")
    p.m.handeye_done(out)
    p.m.command_done(Command.HANDEYE_ADD_POSE, 0, out.code)
    img = p.m.image
    assert p.status() & Status.COMMAND_FAILED and img[r.IR_COMMAND_RESULT] == 205
    assert (img[r.IR_HANDEYE_POSES], img[r.IR_HANDEYE_POSE]) == (7, 8)
    # without ROBOT_POSE_VALID the command carries no pose (the session refuses it)
    p.ctl(EN)
    (effect,) = p.ctl(EN | Control.EXECUTE_COMMAND)
    assert effect == RunCommand(Command.HANDEYE_ADD_POSE, 0)
    p.m.command_done(Command.HANDEYE_ADD_POSE, 0, 209)
    # a calculate's figures; what is not finite goes out as 0
    p.ctl(EN)
    p.m.write(r.HR_COMMAND, [Command.HANDEYE_CALCULATE, 0], p.t)
    (effect,) = p.ctl(EN | Control.EXECUTE_COMMAND)
    p.m.handeye_done(HandEyeOutcome(0, 18, 0, 70000, 0.12, 0.01, 0.4, math.nan, 0.02))
    p.m.command_done(effect.command, 0, 0)
    assert p.status() & Status.COMMAND_DONE and p.u32(r.IR_HANDEYE_VERSION) == 70000
    figures = [c.decode_float32(img[a : a + 2], order) for a in range(
        r.IR_HANDEYE_SIGMA_TRANS, r.IR_COUNT, 2)]
    assert figures == pytest.approx([0.12, 0.01, 0.4, 0.0, 0.02])


def test_command_while_busy_is_refused() -> None:
    p = Plc().ready()
    p.trigger(1)
    p.m.write(r.HR_COMMAND, [Command.RESET, 0], p.t)
    assert p.ctl(EN | Control.TRIGGER | Control.EXECUTE_COMMAND) == []
    assert p.status() & Status.COMMAND_FAILED
    assert p.m.image[r.IR_COMMAND_RESULT] == Reason.BUSY


@pytest.mark.parametrize(
    "outcome",
    [
        answer(0, (1.0, 2.0, math.nan, 0, 0, 0)),
        answer(0, (1.0, 2.0, 3.0)),  # a fanuc offset has 6 values
        answer(0, (1e7, 0, 0, 0, 0, 0)),  # 10 km does not fit the int32 µm block
        answer(70000),
        answer(0, sigma_trans_mm=math.inf),
    ],
)
def test_invalid_outcome_becomes_a_nok_result(outcome: LinkOutcome) -> None:
    p = Plc().ready()
    p.trigger(1)
    p.m.measured(outcome)
    s = p.status()
    assert s & Status.RESULT_VALID and not s & Status.RESULT_OK
    assert p.m.image[r.IR_RESULT_CODE] == Reason.INVALID_OUTCOME
    assert p.m.image[r.IR_OFFSET_INT : r.IR_OFFSET_INT + 12] == [0] * 12


def test_static_registers() -> None:
    p = Plc(WordOrder.CDAB)
    img = p.m.image
    assert img[r.IR_TEST_FLOAT : r.IR_TEST_FLOAT + 2] == [0xE666, 0x42F6]
    assert c.decode_int32(img[r.IR_TEST_INT : r.IR_TEST_INT + 2], WordOrder.CDAB) == r.TEST_INT
    assert img[r.IR_WORD_ORDER] == 1 and img[r.IR_CONVENTION] == 1
    hb = img[r.IR_HEARTBEAT]
    p.m.tick(0.1)
    p.m.tick(0.2)
    assert img[r.IR_HEARTBEAT] == hb + 2


def test_trigger_held_through_a_long_measurement_is_legal() -> None:
    p = Plc(trigger_hold_s=0.3).ready()
    t0 = p.t
    p.trigger(6)
    p.m.tick(t0 + 0.5)  # still measuring, TRIGGER high: allowed
    assert p.m.error is ErrorCode.NONE
    p.m.measured(answer())
    p.m.tick(t0 + 0.7)  # 0.2 s after the answer
    assert p.m.error is ErrorCode.NONE
    p.m.tick(t0 + 0.9)  # 0.4 s after the answer
    assert p.m.error is ErrorCode.TRIGGER_HELD


def test_not_ready_while_trigger_stays_high() -> None:
    p = Plc().ready()
    p.trigger(1)
    p.m.measured(answer())
    p.ctl(EN | Control.TRIGGER | Control.RESULT_ACK)  # acknowledged, TRIGGER not yet dropped
    assert not p.status() & Status.READY and p.m.state is State.READY
    p.ctl(EN | Control.RESULT_ACK)
    assert p.status() & Status.READY


def test_nok_view_ends_the_sequence_with_a_zero_offset_result() -> None:
    p = Plc().ready()
    p.trigger(1, view=1)
    p.m.measured(LinkOutcome(9, 1, (5.0, 5.0, 5.0, 1.0, 1.0, 1.0), views_done=1, final=False))
    s = p.status()
    assert s & Status.RESULT_VALID and not s & (Status.RESULT_OK | Status.VIEW_DONE)
    assert p.u32(r.IR_RESULT_ID) == 1 and p.m.image[r.IR_RESULT_CODE] == 9
    assert p.m.image[r.IR_OFFSET_INT : r.IR_OFFSET_FLOAT + 12] == [0] * 24


def test_abb_full_quaternion_offset_is_sent_without_q1() -> None:
    p = Plc()
    p.m.set_convention(4)  # ABB
    p.ready()
    p.trigger(1)
    q = (-0.999, 0.01, -0.02, 0.03)  # q1 < 0: the same rotation is sent with q1 >= 0
    p.m.measured(answer(0, (1.0, 2.0, 3.0, *q)))
    counts = c.decode_pose_int(p.m.image[r.IR_OFFSET_INT : r.IR_OFFSET_INT + 12], "abb", p.order)
    n = math.sqrt(sum(x * x for x in q))
    assert counts[:3] == (1.0, 2.0, 3.0)
    assert all(abs(a - (-b / n)) < 1e-6 for a, b in zip(counts[3:], q[1:], strict=True))
    assert p.status() & Status.RESULT_OK


def test_abb_robot_pose_arrives_as_the_full_quaternion_and_a_bad_one_is_refused() -> None:
    """The one conversion between the PLC form and the station's: q1 is restored on the way in,
    and a vector part longer than 1 is refused (answered without a measurement)."""
    p = Plc()
    p.m.set_convention(4)  # ABB
    p.ready()
    pose = c.encode_pose_int((10.0, 20.0, 30.0, 0.6, 0.0, 0.0), "abb", p.order)
    p.m.write(r.HR_ROBOT_POSE, pose, p.t)
    (effect,) = p.trigger(1, extra=Control.ROBOT_POSE_VALID)
    assert isinstance(effect, Measure) and effect.refused is None
    assert effect.request.link == "modbus" and effect.request.robot_pose is not None
    assert all(math.isclose(a, b, abs_tol=1e-9) for a, b in
               zip(effect.request.robot_pose, (10.0, 20.0, 30.0, 0.8, 0.6, 0.0, 0.0),
                   strict=True))
    p.m.measured(answer())
    p.ctl(EN | Control.ROBOT_POSE_VALID | Control.RESULT_ACK)
    p.m.write(r.HR_ROBOT_POSE, c.encode_pose_int((0, 0, 0, 0.9, 0.9, 0.0), "abb", p.order), p.t)
    (effect,) = p.trigger(2, extra=Control.ROBOT_POSE_VALID | Control.RESULT_ACK)
    assert isinstance(effect, Measure) and effect.request.robot_pose is None
    assert effect.refused is not None and "norm" in effect.refused
