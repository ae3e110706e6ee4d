"""The trigger/result handshake as a state machine over the fieldbus layout's words, knowing
nothing of sockets or buses.

Inputs are PLC writes to the output block (``write``), clock ticks (``tick``) and completions
(``measured``, ``command_done``); outputs are the input block's words (``image``, read by the
PLC) and effects (``Measure``, ``RunCommand``, ``ResetPipeline``) that the caller runs. Every
method updates the image in one synchronous step, so a reader never sees half of an update.

This is the one place where poses cross between the station's terms and the layout: a robot
pose written by the PLC becomes the :class:`~drivers.links.base.LinkRequest`'s full pose in the
recipe's convention (``codecs.plc_to_pose``), an outcome's offset becomes the 6-value PLC form
(``codecs.pose_to_plc``) before it is scaled into the result block.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mvpose_core.reasons import Reason
from mvpose_core.transforms import RobotConvention

from .. import codecs
from .. import layout as r
from ..base import HandEyeOutcome, LinkOutcome, LinkRequest, VerifyOutcome
from ..layout import Command, Control, ErrorCode, State, Status, VerifyVerdict
from .config import HandshakeConfig


@dataclass(frozen=True)
class Measure:
    request: LinkRequest
    # why the PLC's robot pose cannot be read (an ABB quaternion longer than 1): the trigger is
    # then answered HANDLER_FAILED without a measurement
    refused: str | None = None


@dataclass(frozen=True)
class RunCommand:
    command: Command
    argument: int
    # HANDEYE_ADD_POSE: the flange pose (recipe convention) read with ROBOT_POSE_VALID at the
    # command's edge, or why it cannot be read
    robot_pose: tuple[float, ...] | None = None
    refused: str | None = None


@dataclass(frozen=True)
class ResetPipeline:
    pass


Effect = Measure | RunCommand | ResetPipeline


@dataclass
class HandshakeStats:
    triggers: int = 0
    results: int = 0
    views: int = 0
    missed_triggers: int = 0
    watchdog_trips: int = 0
    held_triggers: int = 0
    commands: int = 0
    commands_failed: int = 0
    invalid_outcomes: int = 0


class Handshake:
    """The device side of the PLC handshake (see docs/plc-interface.md for the timing)."""

    def __init__(self, config: HandshakeConfig, convention_code: int, now: float,
                 link: str = "modbus") -> None:
        self.config = config
        self.link = link
        self.order = config.word_order
        self.image = [0] * r.IR_COUNT
        self.holding = [0] * r.HR_WRITABLE_COUNT
        self.stats = HandshakeStats()
        self._convention = codecs.convention_from_code(convention_code)
        self._flags = Status(0)
        self._busy = False
        self._awaiting_ack = False
        self._command_busy = False
        self._error = ErrorCode.NONE
        self._link_seen = config.watchdog_s == 0
        self._last_beat = now
        self._trigger_since: float | None = None
        self._result_id = 0
        self._recipe = 0
        self._heartbeat = 0
        if config.watchdog_s == 0:
            self._flags |= Status.ONLINE  # no watchdog: the link counts as up from the start
        img = self.image
        img[r.IR_CONVENTION] = convention_code
        img[r.IR_WORD_ORDER] = int(self.order)
        img[r.IR_TEST_FLOAT : r.IR_TEST_FLOAT + 2] = codecs.encode_float32(r.TEST_FLOAT, self.order)
        img[r.IR_TEST_INT : r.IR_TEST_INT + 2] = codecs.encode_int32(r.TEST_INT, self.order)
        self._publish()

    # ------------------------------------------------------------------ derived values

    @property
    def state(self) -> State:
        if self._error:
            return State.ERROR
        if self._busy:
            return State.SINGLE_EXECUTION
        if not self._link_seen:
            return State.PREOPERATIONAL
        if not self.holding[r.HR_CONTROL] & Control.TRIGGER_ENABLE:
            return State.HALTED
        if self._recipe == 0:
            return State.INITIALIZED
        return State.READY

    @property
    def error(self) -> ErrorCode:
        return self._error

    @property
    def recipe(self) -> int:
        return self._recipe

    @property
    def result_id(self) -> int:
        return self._result_id

    def _ready(self, trigger_low: bool = True) -> bool:
        return (
            self.state is State.READY
            and not self._awaiting_ack
            and not self._command_busy
            and not (trigger_low and self.holding[r.HR_CONTROL] & Control.TRIGGER)
        )

    def _online(self, now: float) -> bool:
        wd = self.config.watchdog_s
        return self._link_seen and (wd == 0 or now - self._last_beat <= wd)

    def _publish(self) -> None:
        flags = self._flags & ~(Status.READY | Status.ERROR | Status.BUSY | Status.COMMAND_BUSY)
        if self._ready():
            flags |= Status.READY
        if self._error:
            flags |= Status.ERROR
        if self._busy:
            flags |= Status.BUSY
        if self._command_busy:
            flags |= Status.COMMAND_BUSY
        self._flags = flags
        img = self.image
        img[r.IR_STATUS] = int(flags)
        img[r.IR_STATE] = int(self.state)
        img[r.IR_ERROR_CODE] = int(self._error)
        img[r.IR_RECIPE] = self._recipe

    def set_convention(self, code: int) -> None:
        """The active recipe's robot convention changed (after a recipe selection)."""
        self._convention = codecs.convention_from_code(code)
        self.image[r.IR_CONVENTION] = code

    @property
    def convention(self) -> RobotConvention:
        return self._convention

    def set_recipe(self, recipe: int) -> None:
        self._recipe = recipe
        self._publish()

    # ------------------------------------------------------------------ inputs

    def write(self, address: int, values: list[int], now: float) -> list[Effect]:
        """The PLC wrote ``values`` at holding register ``address`` (already validated)."""
        end = min(address + len(values), r.HR_WRITABLE_COUNT)
        if address >= end:
            return []
        prev_control = self.holding[r.HR_CONTROL]
        prev_beat = self.holding[r.HR_HEARTBEAT]
        self.holding[address:end] = values[: end - address]
        control = self.holding[r.HR_CONTROL]
        rising = Control(control & ~prev_control)
        falling = Control(prev_control & ~control)
        effects: list[Effect] = []

        if self.holding[r.HR_HEARTBEAT] != prev_beat:
            self._last_beat = now
            self._link_seen = True
            self._flags |= Status.ONLINE
        if rising & Control.RESULT_ACK and self._awaiting_ack:
            self._awaiting_ack = False
            self._flags &= ~(Status.RESULT_VALID | Status.VIEW_DONE)
        if rising & Control.ERROR_RESET:
            effects += self._error_reset(now, control)
        if falling & Control.EXECUTE_COMMAND and not self._command_busy:
            self._flags &= ~(Status.COMMAND_DONE | Status.COMMAND_FAILED)
        if rising & Control.EXECUTE_COMMAND:
            effects += self._command()
        if falling & Control.TRIGGER:
            self._flags &= ~Status.TRIGGER_ACK
            self._trigger_since = None
        if rising & Control.TRIGGER:
            effects += self._trigger(now, control)
        self._publish()
        return effects

    def _error_reset(self, now: float, control: int) -> list[Effect]:
        self._flags &= ~Status.MISSED_TRIGGER
        if self._error is ErrorCode.NONE:
            return []
        if self._error is ErrorCode.WATCHDOG and not self._online(now):
            return []
        if self._error is ErrorCode.TRIGGER_HELD and control & Control.TRIGGER:
            return []
        self._error = ErrorCode.NONE
        return [ResetPipeline()]

    def _command(self) -> list[Effect]:
        self._flags &= ~(Status.COMMAND_DONE | Status.COMMAND_FAILED)
        self.stats.commands += 1
        code, arg = self.holding[r.HR_COMMAND], self.holding[r.HR_COMMAND_ARG]
        if self._busy or self._command_busy:
            return self._command_failed(Reason.BUSY)
        try:
            command = Command(code)
        except ValueError:
            return self._command_failed(Reason.UNKNOWN_COMMAND)
        if command is Command.SELECT_RECIPE and arg == 0:
            return self._command_failed(Reason.BAD_ARGUMENT)
        self._command_busy = True
        self.image[r.IR_COMMAND_RESULT] = 0
        if command is Command.VERIFY:  # the block's verdict is the running verify's, once done
            self.image[r.IR_VERIFY_VERDICT] = int(VerifyVerdict.NONE)
        if command is Command.HANDEYE_ADD_POSE:  # the pose comes as a trigger's does
            pose, refused = self._robot_pose(self.holding[r.HR_CONTROL])
            return [RunCommand(command, arg, pose, refused)]
        return [RunCommand(command, arg)]

    def _robot_pose(self, control: int) -> tuple[tuple[float, ...] | None, str | None]:
        """The robot pose registers in the recipe's convention when ROBOT_POSE_VALID is set
        (None otherwise), or why they cannot be read."""
        if not control & Control.ROBOT_POSE_VALID:
            return None, None
        regs = self.holding[r.HR_ROBOT_POSE : r.HR_ROBOT_POSE + 12]
        plc_form = codecs.decode_pose_int(regs, self._convention, self.order)
        try:
            return codecs.plc_to_pose(plc_form, self._convention), None
        except ValueError as err:
            return None, f"robot pose {plc_form}: {err}"

    def _command_failed(self, code: Reason) -> list[Effect]:
        self.stats.commands_failed += 1
        self._flags |= Status.COMMAND_FAILED
        self.image[r.IR_COMMAND_RESULT] = int(code)
        return []

    def _trigger(self, now: float, control: int) -> list[Effect]:
        if not self._ready(trigger_low=False):  # it was low just before this rising edge
            self.stats.missed_triggers += 1
            self._flags |= Status.MISSED_TRIGGER
            return []
        h = self.holding
        trigger_id = codecs.decode_uint32(h[r.HR_TRIGGER_ID : r.HR_TRIGGER_ID + 2], self.order)
        pose, refused = self._robot_pose(control)
        part_id = codecs.decode_ascii(h[r.HR_PART_ID : r.HR_PART_ID + r.PART_ID_CHARS // 2])
        request = LinkRequest(link=self.link, trigger_id=trigger_id, view_index=h[r.HR_VIEW_INDEX],
                              robot_pose=pose, part_id=part_id, recipe=self._recipe)
        self.stats.triggers += 1
        self._busy = True
        self._trigger_since = now
        self._flags &= ~(Status.MISSED_TRIGGER | Status.RESULT_VALID | Status.RESULT_OK)
        self._flags |= Status.TRIGGER_ACK
        self.image[r.IR_TRIGGER_ID : r.IR_TRIGGER_ID + 2] = codecs.encode_uint32(
            trigger_id, self.order
        )
        return [Measure(request, refused)]

    def tick(self, now: float) -> None:
        """Advance the server heartbeat and run the watchdog and the held-trigger watch."""
        self._heartbeat = (self._heartbeat + 1) & 0xFFFF
        self.image[r.IR_HEARTBEAT] = self._heartbeat
        if self._link_seen and not self._online(now) and self._flags & Status.ONLINE:
            self._flags &= ~Status.ONLINE
            self.stats.watchdog_trips += 1
            if not self._error:
                self._error = ErrorCode.WATCHDOG
        hold = self.config.trigger_hold_s
        if self._busy and self._trigger_since is not None:
            # Holding TRIGGER until the answer is a legal PLC style: the hold limit counts from
            # the end of the measurement (to within one tick).
            self._trigger_since = now
        elif (
            hold > 0
            and self._trigger_since is not None
            and self.holding[r.HR_CONTROL] & Control.TRIGGER
            and now - self._trigger_since > hold
        ):
            # Forced reset of the trigger handshake: drop the acknowledgement so the PLC sees it,
            # and refuse triggers until the bit falls and ERROR_RESET is given.
            self._trigger_since = None
            self._flags &= ~Status.TRIGGER_ACK
            self.stats.held_triggers += 1
            if not self._error:
                self._error = ErrorCode.TRIGGER_HELD
        self._publish()

    def measured(self, outcome: LinkOutcome) -> None:
        """Publish the answer to the running trigger: a result block or VIEW_DONE, in one step.

        The offset (recipe convention, full precision; ABB's 7 values) goes out in the PLC form.
        A NOK answer always ends a sequence and carries a zero offset, so a PLC program that
        forgets to test RESULT_OK still never moves the robot by a rejected measurement; an
        outcome that cannot be encoded is published as INVALID_OUTCOME.
        """
        img = self.image
        order = self.order
        code = outcome.result_code
        final = outcome.final
        offset: tuple[float, ...] = (0.0,) * 6
        valid = True
        if code == Reason.OK and outcome.offset is not None:
            try:
                offset = codecs.pose_to_plc(outcome.offset, self._convention)
            except ValueError:
                valid = False
        sigmas = (outcome.sigma_trans_mm, outcome.sigma_rot_deg, outcome.processing_ms)
        if (
            not valid
            or not 0 <= code <= 0xFFFF
            or not all(math.isfinite(x) for x in (*offset, *sigmas))
            or not codecs.fits_int32(offset, self._convention)
        ):
            self.stats.invalid_outcomes += 1
            offset, code, final = (0.0,) * 6, int(Reason.INVALID_OUTCOME), True
            sigmas = (0.0, 0.0, 0.0)
        sigma_trans_mm, sigma_rot_deg, processing_ms = sigmas
        if code != Reason.OK:
            offset = (0.0,) * 6
        views = max(0, min(int(outcome.views_done), 0xFFFF))
        img[r.IR_VIEWS_DONE] = views
        if final or code != Reason.OK:
            # the record's seq: durable across restarts (0: the answer has no record)
            self._result_id = outcome.result_id & 0xFFFFFFFF
            img[r.IR_RESULT_ID : r.IR_RESULT_ID + 2] = codecs.encode_uint32(self._result_id, order)
            img[r.IR_RESULT_CODE] = code
            img[r.IR_PROCESSING_TIME] = min(round(max(processing_ms, 0.0) * 10), 0xFFFF)
            img[r.IR_OFFSET_INT : r.IR_OFFSET_INT + 12] = codecs.encode_pose_int(
                offset, self._convention, order
            )
            img[r.IR_OFFSET_FLOAT : r.IR_OFFSET_FLOAT + 12] = codecs.encode_pose_float(
                offset, order
            )
            img[r.IR_SIGMA_TRANS : r.IR_SIGMA_TRANS + 2] = codecs.encode_int32(
                _clamp_int32(sigma_trans_mm * 1e3), order
            )
            img[r.IR_SIGMA_ROT : r.IR_SIGMA_ROT + 2] = codecs.encode_int32(
                _clamp_int32(sigma_rot_deg * 1e4), order
            )
            self._flags |= Status.RESULT_VALID
            if code == Reason.OK:
                self._flags |= Status.RESULT_OK
            self.stats.results += 1
        else:
            self._flags |= Status.VIEW_DONE
            self.stats.views += 1
        self._flags ^= Status.DONE_TOGGLE
        self._busy = False
        self._awaiting_ack = True
        self._publish()

    def command_done(self, command: Command, argument: int, result: int) -> None:
        """Publish a command's end: COMMAND_DONE when ``result`` is 0, else COMMAND_FAILED."""
        self._command_busy = False
        result = max(0, min(int(result), 0xFFFF))
        self.image[r.IR_COMMAND_RESULT] = result
        if result == 0:
            if command is Command.SELECT_RECIPE:
                self._recipe = argument
            self._flags |= Status.COMMAND_DONE
        else:
            self.stats.commands_failed += 1
            self._flags |= Status.COMMAND_FAILED
        self._publish()

    def verified(self, outcome: VerifyOutcome) -> None:
        """Publish a verify's block (registers 50-69); :meth:`command_done` follows with its
        code. Without a verdict the block holds the record's id, NONE and zeros."""
        img = self.image
        order = self.order
        difference: tuple[float, ...] = (0.0,) * 6
        figures = (outcome.displacement_mm, outcome.rotation_deg)
        judged = outcome.result_code == 0 and outcome.difference is not None
        if judged and outcome.difference is not None:
            try:
                difference = codecs.pose_to_plc(outcome.difference, self._convention)
            except ValueError:
                judged = False
        if not all(math.isfinite(x) for x in (*difference, *figures)):
            judged = False
        if not judged:
            difference, figures = (0.0,) * 6, (0.0, 0.0)
        verdict = VerifyVerdict.NONE
        if judged:
            verdict = VerifyVerdict.PASSED if outcome.passed else VerifyVerdict.FAILED
        img[r.IR_VERIFY_RESULT_ID : r.IR_VERIFY_RESULT_ID + 2] = codecs.encode_uint32(
            outcome.result_id & 0xFFFFFFFF, order)
        img[r.IR_VERIFY_VERDICT] = int(verdict)
        img[r.IR_VERIFY_DIFFERENCE : r.IR_VERIFY_DIFFERENCE + 12] = codecs.encode_pose_float(
            difference, order)
        img[r.IR_VERIFY_DISPLACEMENT : r.IR_VERIFY_DISPLACEMENT + 2] = codecs.encode_float32(
            figures[0], order)
        img[r.IR_VERIFY_ROTATION : r.IR_VERIFY_ROTATION + 2] = codecs.encode_float32(
            figures[1], order)

    def handeye_done(self, outcome: HandEyeOutcome) -> None:
        """Publish a hand-eye step's block (registers 70-83); :meth:`command_done` follows
        with its code. Figures that are not finite go out as 0."""
        img = self.image
        order = self.order
        img[r.IR_HANDEYE_POSES] = max(0, min(int(outcome.poses), 0xFFFF))
        img[r.IR_HANDEYE_POSE] = max(0, min(int(outcome.pose), 0xFFFF))
        img[r.IR_HANDEYE_VERSION : r.IR_HANDEYE_VERSION + 2] = codecs.encode_uint32(
            int(outcome.version) & 0xFFFFFFFF, order)
        for at, x in ((r.IR_HANDEYE_SIGMA_TRANS, outcome.sigma_mm),
                      (r.IR_HANDEYE_SIGMA_ROT, outcome.sigma_deg),
                      (r.IR_HANDEYE_HOLDOUT_PX, outcome.holdout_rms_px),
                      (r.IR_HANDEYE_HOLDOUT_MM, outcome.holdout_mm),
                      (r.IR_HANDEYE_HOLDOUT_DEG, outcome.holdout_deg)):
            img[at : at + 2] = codecs.encode_float32(x if math.isfinite(x) else 0.0, order)

    def pipeline_reset_failed(self) -> None:
        if not self._error:
            self._error = ErrorCode.INTERNAL
        self._publish()


def _clamp_int32(x: float) -> int:
    return max(-(2**31), min(2**31 - 1, round(x)))
