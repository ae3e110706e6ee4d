"""The VisionSystem's state machines and its jobs: what the methods of
``VisionStateMachine`` and ``AutomaticModeStateMachine`` do, and mvpose's own Measure and Verify.

- ``VisionStateMachine``: Operational with its automatic mode (Initialized: no recipe selected,
  Ready, SingleExecution while a single job of this link runs, ContinuousExecution between
  ``StartContinuous`` and ``Stop`` / ``Abort``), Halted after ``Halt`` until ``Reset``;
- ``AutomaticModeStateMachine.StartSingleJob``: one trigger (the same ``StationHandler.measure``
  as Modbus), answered at once with its JobId; the result follows as a ``ResultReadyEvent``
  (:mod:`.results`); ``StartContinuous``: triggers back to back, each a normal trigger with its
  record and event; ``VisionSystem.Measure`` (mvpose's own method) triggers and waits for the
  outcome; ``VisionSystem.Verify`` (mvpose's own) measures the taught reference part and judges
  it; ``RecipeManagement.PrepareRecipe`` selects a recipe;
- ``SystemState``: the SEMI E10 state (production while a job runs, stand-by, scheduled downtime
  while halted).

The states are shown in the address space's nodes (:class:`~.model.Model`); the address space
(:mod:`.model`) links the methods below to the model's method nodes.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable
from typing import Any

from asyncua import ua

from mvpose_core.reasons import Reason, reason_name

from ..base import LinkOutcome, LinkRequest, RecipeInfo, StationHandler, VerifyOutcome
from . import values as v
from .model import Model
from .settings import OpcUaLinkConfig

log = logging.getLogger(__name__)

_UA: Any = ua  # the NodeSet's structures are made at import time; asyncua's stubs are strict


class VisionMachine:
    """The VisionSystem's states and the jobs it runs through the station. ``spawn`` runs a
    coroutine as the link's task, ``error`` keeps a text among the link's last errors, ``live``
    says whether the server is up (the states are shown only then)."""

    def __init__(self, config: OpcUaLinkConfig, handler: StationHandler, model: Model,
                 spawn: Callable[[Any], asyncio.Future[Any]], error: Callable[[str], None],
                 live: Callable[[], bool]) -> None:
        self.config = config
        self.handler = handler
        self.model = model
        self.spawn = spawn
        self.error = error
        self.live = live
        self.state = "Preoperational"
        self.auto_state = "Initialized"
        self.jobs = 0  # single jobs of this link running (StartSingleJob, Measure)
        self.triggers = 0
        self._trigger_id = 0
        self.continuous: asyncio.Future[Any] | None = None  # StartContinuous's loop
        self.stop_requested = False

    # ------------------------------------------------------------------ states
    async def show_states(self) -> None:
        if self.state == "Operational":
            self.auto_state = ("ContinuousExecution" if self.continuous is not None else
                               "SingleExecution" if self.jobs else
                               "Ready" if self.handler.selected_recipe() else "Initialized")
        for key, state in (("sm_state", self.state), ("auto_state", self.auto_state)):
            node = self.model.nodes[key]
            active = key == "sm_state" or self.state == "Operational"
            text = state if active else ""
            await node.write_value(ua.LocalizedText(text))
            await (await node.get_child("0:Id")).write_value(
                self.model.state_ids[state] if active else ua.NodeId())
        await self.model.nodes["system_state"].write_value(
            ua.Variant(v.system_state(self.state, self.auto_state)))

    async def selected(self) -> RecipeInfo | None:
        return next((r for r in await self.handler.recipes() if r.selected), None)

    async def show_recipe(self) -> None:
        number = self.handler.selected_recipe()
        current = await self.selected()
        name, version = (current.name, current.version) if current else ("", 0)
        n = self.model.nodes
        await n["recipe.Number"].write_value(ua.Variant(number, ua.VariantType.UInt16))
        await n["recipe.Name"].write_value(ua.Variant(name, ua.VariantType.String))
        await n["recipe.Version"].write_value(ua.Variant(version, ua.VariantType.UInt32))
        await n["recipe.Convention"].write_value(
            ua.Variant(self.handler.convention().value if number else "", ua.VariantType.String))
        if self.live():
            await self.show_states()

    # ------------------------------------------------------------------ methods
    async def halt(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        self.state = "Halted"
        await self.end_continuous()
        await self.show_states()
        return [v.int32(0)]

    async def reset(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        await self.end_continuous()
        await self.handler.reset()
        self.state = "Operational"
        await self.show_states()
        return [v.int32(0)]

    async def select_auto(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        if self.state == "Halted":
            return [v.int32(int(Reason.BUSY))]
        self.state = "Operational"  # automatic is the station's only mode
        await self.show_states()
        return [v.int32(0)]

    async def prepare_recipe(self, parent: ua.NodeId, external: ua.Variant,
                              internal: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        wanted = v.struct_id(external.Value) or v.struct_id(internal.Value)
        code = int(Reason.BAD_ARGUMENT)
        if wanted.isdigit() and 0 < int(wanted) <= 65535:
            code = await self.handler.select_recipe(int(wanted))
        if code == 0:
            await self.show_recipe()
        current = await self.selected()
        out = (v.recipe_id("RecipeIdInternalDataType", current.name, current.version,
                           current.sha256, current.number)
               if current else _UA.RecipeIdInternalDataType(Id=""))
        return [ua.Variant(out), ua.Variant(code == 0, ua.VariantType.Boolean), v.int32(code)]

    async def start_single_job(self, parent: ua.NodeId, meas: ua.Variant, part: ua.Variant,
                                recipe: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        number = v.struct_id(recipe.Value)
        if self.state != "Operational" or self.continuous is not None:
            return [ua.Variant(_UA.JobIdDataType(Id="")), v.int32(int(Reason.BUSY))]
        if number and not number.isdigit():
            return [ua.Variant(_UA.JobIdDataType(Id="")), v.int32(int(Reason.BAD_ARGUMENT))]
        trigger_id = self.next_trigger(v.struct_id(meas.Value))
        req = self._request(trigger_id, v.struct_id(part.Value), int(number or 0))
        self.spawn(self._job(req))
        return [ua.Variant(_UA.JobIdDataType(Id=str(trigger_id))), v.int32(0)]

    # ------------------------------------------------------------------ continuous mode
    async def start_continuous(self, parent: ua.NodeId, meas: ua.Variant, part: ua.Variant,
                                recipe: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        """Triggers back to back until Stop, Abort, Halt or Reset: each one a normal trigger
        (its record, its event), the next one asked for once the station has answered the
        last, so a trigger of another link (Modbus) waits for one job at most."""
        none = ua.Variant(_UA.JobIdDataType(Id=""))
        number = v.struct_id(recipe.Value)
        if self.state != "Operational" or self.continuous is not None or self.jobs:
            return [none, v.int32(int(Reason.BUSY))]
        if number and not number.isdigit():
            return [none, v.int32(int(Reason.BAD_ARGUMENT))]
        known = {r.number for r in await self.handler.recipes()}
        if (int(number) not in known) if number else not self.handler.selected_recipe():
            # refused here rather than recorded over and over as UNKNOWN_RECIPE
            self.error(f"StartContinuous: no recipe {number or '(none selected)'}")
            return [none, v.int32(int(Reason.UNKNOWN_RECIPE))]
        first = self.next_trigger(v.struct_id(meas.Value))
        self.stop_requested = False
        self.continuous = self.spawn(
            self._run_continuous(first, v.struct_id(part.Value), int(number or 0)))
        await self.show_states()
        return [ua.Variant(_UA.JobIdDataType(Id=str(first))), v.int32(0)]

    async def _run_continuous(self, first: int, part_id: str, recipe: int) -> None:
        trigger_id = first
        try:
            while not self.stop_requested and self.state == "Operational":
                # its own task, shielded: Abort ends the loop, never a job inside the station
                job = self.spawn(self._job(self._request(trigger_id, part_id, recipe),
                                            single=False))
                out = await asyncio.shield(job)
                if out.result_code >= 1000:  # the link's own range: the station did not answer
                    self.error(f"continuous mode ended: trigger {trigger_id} was answered "
                                f"{reason_name(out.result_code)} by the link itself")
                    break
                trigger_id = self.next_trigger("")
        finally:
            self.continuous = None
            if self.live():
                await self.show_states()

    async def stop_continuous(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        """The running job ends with its record; then Ready (the call returns then)."""
        task = self.continuous
        if task is None:
            return [v.int32(int(Reason.BAD_ARGUMENT))]  # nothing runs
        self.stop_requested = True
        await asyncio.wait({task})  # a failed loop is logged by _spawn's callback
        return [v.int32(0)]

    async def abort(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        """Ready at once; a half-done multi-view sequence is dropped (as Reset); a job already
        in the station still ends with its record and event."""
        if self.continuous is None:
            return [v.int32(int(Reason.BAD_ARGUMENT))]
        await self.end_continuous()
        await self.handler.reset()
        await self.show_states()
        return [v.int32(0)]

    async def end_continuous(self) -> None:
        task = self.continuous
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def measure(self, parent: ua.NodeId, part: ua.Variant, recipe: ua.Variant,
                       trigger: ua.Variant) -> list[ua.Variant]:
        if self.state != "Operational":
            out = LinkOutcome(int(Reason.BUSY), 0)
        else:
            req = self._request(self.next_trigger(str(trigger.Value or "")), str(part.Value or ""),
                                int(recipe.Value or 0))
            # shielded: a client that goes away mid-measurement does not cancel the record
            out = await asyncio.shield(self.spawn(self._job(req)))
        offset = list(out.offset) if out.offset is not None else []
        return [ua.Variant(out.result_id, ua.VariantType.UInt32), v.int32(out.result_code),
                ua.Variant(offset, ua.VariantType.Double),
                ua.Variant(out.sigma_trans_mm, ua.VariantType.Double),
                ua.Variant(out.sigma_rot_deg, ua.VariantType.Double)]

    async def verify(self, parent: ua.NodeId) -> list[ua.Variant]:
        """mvpose's Verify: the taught reference part measured now and judged (ResultCode 0:
        judged, Passed is the verdict; else why there is no verdict)."""
        if self.state != "Operational":
            out = VerifyOutcome(int(Reason.BUSY), 0, message=f"the vision system is {self.state}")
        else:
            limit = self.config.measure_timeout_s
            try:  # shielded: a client that goes away mid-verify does not cancel the record
                out = await asyncio.shield(self.spawn(asyncio.wait_for(
                    self.handler.verify("opcua", "opcua"), limit)))
            except TimeoutError:
                out = VerifyOutcome(int(Reason.TIMEOUT), 0,
                                    message=f"no verify within {limit} s (OPC UA link)")
            except Exception as err:  # noqa: BLE001 - the caller gets the reason
                log.exception("OPC UA verify failed")
                out = VerifyOutcome(int(Reason.HANDLER_FAILED), 0,
                                    message=f"{type(err).__name__}: {err}")
        return [v.uint32(out.result_id), v.int32(out.result_code),
                ua.Variant(out.passed, ua.VariantType.Boolean),
                ua.Variant(list(out.difference or ()), ua.VariantType.Double),
                ua.Variant(out.displacement_mm, ua.VariantType.Double),
                ua.Variant(out.rotation_deg, ua.VariantType.Double),
                ua.Variant(out.message, ua.VariantType.String)]

    def next_trigger(self, wanted: str) -> int:
        if wanted.isdigit() and 0 < int(wanted) < 2**32:
            return int(wanted)
        self._trigger_id = self._trigger_id % (2**32 - 1) + 1
        return self._trigger_id

    def _request(self, trigger_id: int, part_id: str, recipe: int) -> LinkRequest:
        return LinkRequest(link="opcua", trigger_id=trigger_id, view_index=0, robot_pose=None,
                           part_id=part_id, recipe=recipe)

    async def _job(self, req: LinkRequest, single: bool = True) -> LinkOutcome:
        """One trigger through the station, with the link's own recorded backstop."""
        self.triggers += 1
        self.jobs += single
        await self.show_states()
        t0 = time.monotonic()
        try:
            limit = self.config.measure_timeout_s
            try:
                return await asyncio.wait_for(self.handler.measure(req), limit)
            except TimeoutError:
                code, text = int(Reason.TIMEOUT), f"no answer within {limit} s (OPC UA link)"
            except Exception as err:  # noqa: BLE001 - recorded with its text
                log.exception("OPC UA trigger %d failed", req.trigger_id)
                code, text = int(Reason.HANDLER_FAILED), f"{type(err).__name__}: {err}"
            self.error(f"trigger {req.trigger_id}: {text}")
            ms = (time.monotonic() - t0) * 1e3
            rid = await self.handler.record_failure(req, code, text, ms)
            return LinkOutcome(code, rid, processing_ms=ms)
        finally:
            self.jobs -= single
            if self.live():
                await self.show_states()
