"""mvpose's hand-eye methods on the VisionSystem: HandEyeBegin, HandEyeAddPose, HandEyeCalculate.

The robot-driven hand-eye session (docs/calibration.md, "Robot-driven hand-eye") for a robot or
cell controller that speaks OPC UA: the same steps and codes as the PLC's commands and REST.
The three methods answer alike (ResultCode: 0 or the session's code, the poses held, the pose
the step was about, the stored calibration version after a calculate with its 1σ and hold-out
figures, and the message). They are engineer methods: a calibration is an engineer's work,
even though its result still waits for an activation.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from asyncua import Node, ua

from mvpose_core.reasons import Reason

from ..base import HandEyeOutcome, StationHandler
from . import values as v

log = logging.getLogger(__name__)

#: a calculate solves and writes the report: give it more than a measurement
CALCULATE_S = 300.0


def _outputs() -> list[ua.Argument]:
    d = ua.ObjectIds.Double
    return [v.arg("ResultCode", ua.ObjectIds.Int32), v.arg("Poses", ua.ObjectIds.UInt32),
            v.arg("Pose", ua.ObjectIds.UInt32), v.arg("CalibrationVersion", ua.ObjectIds.UInt32),
            v.arg("SigmaTranslationMm", d), v.arg("SigmaRotationDeg", d),
            v.arg("HoldOutRmsPx", d), v.arg("HoldOutMm", d), v.arg("HoldOutDeg", d),
            v.arg("Message", ua.ObjectIds.String)]


def _answer(out: HandEyeOutcome) -> list[ua.Variant]:
    d = ua.VariantType.Double
    return [v.int32(out.code), v.uint32(out.poses), v.uint32(out.pose), v.uint32(out.version),
            ua.Variant(out.sigma_mm, d), ua.Variant(out.sigma_deg, d),
            ua.Variant(out.holdout_rms_px, d), ua.Variant(out.holdout_mm, d),
            ua.Variant(out.holdout_deg, d), ua.Variant(out.message, ua.VariantType.String)]


class HandEyeMethods:
    """The three methods, calling the station's handler; ``operational`` says whether the
    vision system takes work now, ``spawn`` runs a call shielded from a client that leaves."""

    def __init__(self, handler: StationHandler, operational: Callable[[], str | None],
                 spawn: Callable[[Awaitable[HandEyeOutcome]], asyncio.Future[HandEyeOutcome]],
                 timeout_s: float) -> None:
        self.handler = handler
        self.operational = operational
        self.spawn = spawn
        self.timeout_s = timeout_s

    async def add(self, vs: Node, idx: int) -> list[ua.NodeId]:
        """Add the methods under the VisionSystem; their node ids (engineer methods)."""
        out = _outputs()
        nodes = [
            await vs.add_method(idx, "HandEyeBegin", self._begin,
                                [v.arg("HoldOut", ua.ObjectIds.UInt16)], out),
            await vs.add_method(idx, "HandEyeAddPose", self._add_pose,
                                [v.arg("Pose", ua.ObjectIds.Double, rank=1)], out),
            await vs.add_method(idx, "HandEyeCalculate", self._calculate, [], out),
        ]
        return [n.nodeid for n in nodes]

    async def _begin(self, parent: ua.NodeId, holdout: ua.Variant) -> list[ua.Variant]:
        # HoldOut 0 asks for the default; a session without a check is a REST or PLC choice
        n = int(holdout.Value or 0)
        return await self._run(self.handler.handeye_begin("opcua", "opcua", n or None),
                               self.timeout_s)

    async def _add_pose(self, parent: ua.NodeId, pose: ua.Variant) -> list[ua.Variant]:
        values: Any = pose.Value
        robot_pose = tuple(float(x) for x in values) if values else None
        return await self._run(self.handler.handeye_add_pose("opcua", "opcua", robot_pose),
                               self.timeout_s)

    async def _calculate(self, parent: ua.NodeId) -> list[ua.Variant]:
        return await self._run(self.handler.handeye_calculate("opcua", "opcua"), CALCULATE_S)

    async def _run(self, call: Awaitable[HandEyeOutcome], limit: float) -> list[ua.Variant]:
        busy = self.operational()
        if busy is not None:
            close = getattr(call, "close", None)
            if close is not None:
                close()  # the coroutine never runs
            return _answer(HandEyeOutcome(int(Reason.BUSY), message=busy))
        try:  # shielded: a client that goes away mid-step does not cancel it
            out = await asyncio.shield(self.spawn(asyncio.wait_for(call, limit)))
        except TimeoutError:
            out = HandEyeOutcome(int(Reason.TIMEOUT),
                                 message=f"no answer within {limit:g} s (OPC UA link)")
        except Exception as err:  # noqa: BLE001 - the caller gets the reason
            log.exception("OPC UA hand-eye step failed")
            out = HandEyeOutcome(int(Reason.HANDLER_FAILED), message=f"{type(err).__name__}: {err}")
        return _answer(out)
