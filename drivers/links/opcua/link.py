"""The OPC UA link itself: the server, the VisionSystem object, its states, triggers and events.

One ``VisionSystem`` object (``VisionSystemType`` of the OPC Foundation's Machine Vision NodeSet,
:mod:`.nodesets`) stands for the station:

- ``VisionStateMachine``: Operational with its automatic mode (Initialized: no recipe selected,
  Ready, SingleExecution while a single job of this link runs, ContinuousExecution between
  ``StartContinuous`` and ``Stop`` / ``Abort``), Halted after ``Halt`` until ``Reset``;
- ``AutomaticModeStateMachine.StartSingleJob``: one trigger (the same ``StationHandler.measure``
  as Modbus), answered at once with its JobId; the result follows as a ``ResultReadyEvent``;
  ``StartContinuous``: triggers back to back, each a normal trigger with its record and event;
  ``VisionSystem.Measure`` (mvpose's own method) triggers and waits for the outcome;
- ``RecipeManagement``, ``ResultManagement``, ``ConfigurationManagement``: :mod:`.management`;
  a ``ResultReadyEvent`` (our subtype ``MvposeResultReadyEventType``) for every recorded answer
  whichever link or client caused it, ``ResultId`` = the record's seq, notified through the
  VisionSystem and the Server object; the last result also as variables
  (``ResultManagement/LastResult``);
- ``SystemState``: the SEMI E10 state (production while a job runs, stand-by, scheduled downtime
  while halted).

Security (:mod:`.access`, :mod:`.certificates`): Basic256Sha256 Sign / SignAndEncrypt by
default with a server certificate made at the first start in ``pki_dir``; client certificates
must be in ``<pki_dir>/trusted`` (refused ones land in ``<pki_dir>/rejected``); users log in
with a name and password checked against the station file's pbkdf2 hashes and get the read,
operator (may call methods) or engineer role (also ActivateConfiguration, writes); no session on
a channel whose security the station file does not list (None among them). In a station the
server runs in a process of its own (:mod:`drivers.links.process`): building and encoding each
result event is pure Python that would otherwise hold the station process's GIL beside the
trigger path.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua

from mvpose_core.reasons import Reason, reason_name

from ..base import (
    AlarmNotice,
    Link,
    LinkOutcome,
    LinkRequest,
    RecipeInfo,
    StationHandler,
    VerifyOutcome,
)
from ..result import ResultEvent
from . import values as v
from .access import Roles, Users, keep_unlisted_to_discovery
from .arguments import check_arguments
from .certificates import make_certificate, validate_clients
from .conditions import AlarmConditions
from .events import standard_event_filters
from .handeye import HandEyeMethods
from .management import Management
from .nodesets import MACHINE_VISION, MV_URI, MVPOSE_URI, complete_definitions, import_order
from .settings import OpcUaLinkConfig

log = logging.getLogger(__name__)

POLICIES = {
    "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    "None": ua.SecurityPolicyType.NoSecurity,
}
_UA: Any = ua  # the NodeSet's structures are made at import time; asyncua's stubs are strict


class OpcUaLink(Link):
    """OPC UA server with the station's VisionSystem object."""

    name = "opcua"
    config: OpcUaLinkConfig

    def __init__(self, config: OpcUaLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.server: Server | None = None
        self.port_bound = 0
        self.load_s: dict[str, float] = {}
        self.state = "Preoperational"
        self.auto_state = "Initialized"
        self.jobs = 0  # single jobs of this link running (StartSingleJob, Measure)
        self.results = 0  # ResultReadyEvents sent
        self.triggers = 0
        self.last_errors: list[str] = []
        self._listening = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Future[Any]] = set()
        self._trigger_id = 0
        self._nodes: dict[str, Node] = {}
        self._state_ids: dict[str, ua.NodeId] = {}
        self._evgen: Any = None
        self.conditions = AlarmConditions()  # the station's alarms as condition events
        self._lock = asyncio.Lock()  # variable writes and events in order
        self._t0 = 0.0
        self._order: list[Path] = []
        self._pki: Path | None = None
        self._boot_task: asyncio.Future[Any] | None = None
        self.started = threading.Event()  # the endpoint listens (for threads and other loops)
        self.failed: str | None = None
        self._made: Server | None = None
        self._roles = Roles(config)
        self.management = Management(handler, self._show_recipe, self._error,
                                     config.query_spacing_s)
        self._continuous: asyncio.Future[Any] | None = None  # StartContinuous's loop
        self._stop_requested = False

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> None:
        """Check at once what can fail (the NodeSets against their pinned hashes, the server
        certificate), then build and open the server in the background: importing the Machine
        Vision NodeSet takes seconds (docs/opcua.md), more than a station gives its links
        to start. Until the endpoint listens, ready() is False and status() says starting."""
        self._loop = asyncio.get_running_loop()
        self._t0 = time.monotonic()
        self._order = import_order()
        if any(p != "None" for p in self.config.security):
            self._pki = await make_certificate(self.config)
        self._boot_task = self._spawn(self._boot())

    async def wait_ready(self, timeout_s: float) -> None:
        """Until the endpoint listens (on the station's loop); raises what the start raised."""
        if self._boot_task is not None:
            await asyncio.wait_for(asyncio.shield(self._boot_task), timeout_s)

    async def _boot(self) -> None:
        cfg = self.config
        try:
            t = time.monotonic()
            server = self._made = Server(user_manager=Users(cfg))
            await server.init()
            self.load_s["init"] = time.monotonic() - t
            server.set_server_name("mvpose station")
            await server.set_application_uri(cfg.application_uri)
            server.set_endpoint(f"opc.tcp://{cfg.host}:{cfg.port}/mvpose")
            server.set_security_policy([POLICIES[p] for p in cfg.security],
                                       permission_ruleset=self._roles)
            tokens: list[type] = [ua.UserNameIdentityToken]
            if cfg.allow_anonymous:
                tokens.append(ua.AnonymousIdentityToken)
            server.set_identity_tokens(tokens)
            if self._pki is not None:
                await validate_clients(server, self._pki,
                                       self.config.trust_all_client_certificates, self._error)
            keep_unlisted_to_discovery(server, [POLICIES[p] for p in cfg.security],
                                       list(POLICIES.values()))
            t = time.monotonic()
            for path in self._order:
                await server.import_xml(str(path), strict_mode=path.name == MACHINE_VISION)
            await complete_definitions(server)
            self.load_s["nodesets"] = time.monotonic() - t
            t = time.monotonic()
            await self._build(server)
            self.load_s["model"] = time.monotonic() - t
            await server.start()
        except Exception as err:
            self.failed = f"the OPC UA server did not start: {type(err).__name__}: {err}"
            log.error("%s", self.failed, exc_info=True)
            raise
        self.server = server
        self.port_bound = server.bserver.port if server.bserver is not None else cfg.port
        self.state = "Operational"
        await self._show_recipe()
        await self.management.show_configuration()
        self._listening = True
        self.handler.add_listener(self._on_result)
        self.load_s["total"] = time.monotonic() - self._t0
        self.started.set()
        log.info("OPC UA link on opc.tcp://%s:%d/mvpose (%s); started in %s s", cfg.host,
                 self.port_bound, ", ".join(cfg.security),
                 {k: round(v, 2) for k, v in self.load_s.items()})

    async def stop(self) -> None:
        self._listening = False  # the station has no remove_listener: the callback goes quiet
        await self._end_continuous()
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        made, self._made, self.server = self._made, None, None
        if made is not None and made.bserver is not None:  # it listens (or did)
            await made.stop()

    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("the OPC UA link is not started")
        return self.port_bound

    def ready(self) -> bool:
        return self.server is not None

    def status(self) -> dict[str, Any]:
        if self.server is None:
            starting = self._boot_task is not None and not self._boot_task.done()
            return {"running": False, "starting": starting, "error": self.failed}
        return {
            "running": True, "port": self.port_bound, "security": list(self.config.security),
            "state": self.state, "automatic_mode": self.auto_state, "triggers": self.triggers,
            "continuous": self._continuous is not None,
            "results_published": self.results, "alarms_published": self.conditions.sent,
            "start_s": {k: round(v, 2) for k, v in self.load_s.items()},
            "last_errors": self.last_errors[-5:],
        }

    def alarm_changed(self, notice: AlarmNotice) -> None:
        if self.server is not None:
            self._spawn(self._publish_alarm(notice))

    async def _publish_alarm(self, notice: AlarmNotice) -> None:
        async with self._lock:
            if self.server is not None:
                await self.conditions.publish(self.server, notice)

    def recipe_changed(self) -> None:
        if self.server is not None:
            self._spawn(self._show_recipe())
            # a calibration activated elsewhere (REST) comes with the same call
            self._spawn(self.management.show_configuration())

    # ------------------------------------------------------------------ the address space
    async def _build(self, server: Server) -> None:
        mv = await server.get_namespace_index(MV_URI)
        idx = await server.register_namespace(MVPOSE_URI)
        types = server.nodes.base_object_type
        vst = await types.get_child([f"{mv}:VisionSystemType"])
        vs = await server.nodes.objects.add_object(_UA.NodeId("VisionSystem", idx),
                                                   f"{mv}:VisionSystem", objecttype=vst.nodeid)
        await vs.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        sm = await vs.get_child(f"{mv}:VisionStateMachine")
        auto = await sm.get_child(f"{mv}:AutomaticModeStateMachine")
        rm = await vs.get_child(f"{mv}:RecipeManagement")
        res = await vs.get_child(f"{mv}:ResultManagement")
        n = self._nodes
        n["vs"], n["sm"], n["auto"] = vs, sm, auto
        n["sm_state"] = await sm.get_child("0:CurrentState")
        n["system_state"] = await vs.get_child(f"{mv}:SystemState")
        n["auto_state"] = await auto.get_child("0:CurrentState")
        sm_type = server.get_node(v.typedef(await sm.read_type_definition()))
        auto_type = server.get_node(v.typedef(await auto.read_type_definition()))
        for state in ("Preoperational", "Halted", "Error", "Operational"):
            self._state_ids[state] = (await sm_type.get_child(f"{mv}:{state}")).nodeid
        for state in ("Initialized", "Ready", "SingleExecution", "ContinuousExecution"):
            self._state_ids[state] = (await auto_type.get_child(f"{mv}:{state}")).nodeid

        # methods of the standard: the state machines and PrepareRecipe here, the rest of the
        # management objects in .management
        links: dict[tuple[Node, str], Callable[..., Any]] = {
            (sm, "Halt"): self._halt, (sm, "Reset"): self._reset,
            (sm, "SelectModeAutomatic"): self._select_auto,
            (auto, "StartSingleJob"): self._start_single_job,
            (auto, "StartContinuous"): self._start_continuous,
            (auto, "Stop"): self._stop_continuous, (auto, "Abort"): self._abort,
            (rm, "PrepareRecipe"): self._prepare_recipe,
        }
        for (parent, method), fn in links.items():
            server.link_method(await parent.get_child(f"{mv}:{method}"), fn)
        await self.management.build(server, vs, mv)
        self._roles.engineer_methods = self.management.engineer_methods
        await _not_implemented(server, vs)

        # mvpose's own: the active recipe, the last result, Measure, the event subtype
        recipe = await rm.add_object(idx, "ActiveRecipe")
        for name, value, vt in (("Number", 0, ua.VariantType.UInt16),
                                ("Name", "", ua.VariantType.String),
                                ("Version", 0, ua.VariantType.UInt32),
                                ("Convention", "", ua.VariantType.String)):
            n[f"recipe.{name}"] = await recipe.add_variable(idx, name, ua.Variant(value, vt))
        last = await res.add_object(idx, "LastResult")
        for name, value, vt in self._result_fields():
            n[f"last.{name}"] = await last.add_variable(idx, name, ua.Variant(value, vt))
        measure = await vs.add_method(
            idx, "Measure", self._measure,
            [v.arg("PartId", ua.ObjectIds.String), v.arg("RecipeNumber", ua.ObjectIds.UInt16),
             v.arg("TriggerId", ua.ObjectIds.UInt32)],
            [v.arg("ResultId", ua.ObjectIds.UInt32), v.arg("ResultCode", ua.ObjectIds.Int32),
             v.arg("Offset", ua.ObjectIds.Double, rank=1),
             v.arg("SigmaTranslationMm", ua.ObjectIds.Double),
             v.arg("SigmaRotationDeg", ua.ObjectIds.Double)])
        n["measure"] = measure
        n["verify"] = await vs.add_method(
            idx, "Verify", self._verify, [],
            [v.arg("ResultId", ua.ObjectIds.UInt32), v.arg("ResultCode", ua.ObjectIds.Int32),
             v.arg("Passed", ua.ObjectIds.Boolean),
             v.arg("Difference", ua.ObjectIds.Double, rank=1),
             v.arg("DisplacementMm", ua.ObjectIds.Double),
             v.arg("RotationDeg", ua.ObjectIds.Double), v.arg("Message", ua.ObjectIds.String)])
        handeye = HandEyeMethods(
            self.handler, lambda: None if self.state == "Operational"
            else f"the vision system is {self.state}", self._spawn,
            self.config.measure_timeout_s or 30.0)
        self._roles.engineer_methods.update(await handeye.add(vs, idx))
        rre = await types.get_child(["0:BaseEventType", f"{mv}:ResultReadyEventType"])
        props = [(name, vt) for name, _, vt in self._result_fields()
                 if name not in ("PartId", "CreationTime")]
        etype = await server.create_custom_event_type(idx, "MvposeResultReadyEventType",
                                                      rre.nodeid, props)
        self._evgen = await server.get_event_generator(etype, vs.nodeid)
        await self.conditions.build(server, vs, mv)
        await check_arguments(server, vs)
        # the Server object notifies every event of the VisionSystem too (OPC 10000-3 §7.16:
        # the notifier hierarchy), and OfType filters match subtypes (.events)
        await server.nodes.server.add_reference(vs.nodeid, ua.ObjectIds.HasNotifier)
        standard_event_filters(server)

    @staticmethod
    def _result_fields() -> list[tuple[str, Any, ua.VariantType]]:
        return [
            ("ResultNumber", 0, ua.VariantType.UInt32), ("TriggerId", 0, ua.VariantType.UInt32),
            ("PartId", "", ua.VariantType.String), ("Recipe", "", ua.VariantType.String),
            ("ResultCode", 0, ua.VariantType.Int32), ("Reason", "", ua.VariantType.String),
            ("ResultMessage", "", ua.VariantType.String),
            ("Offset", [], ua.VariantType.Double), ("Convention", "", ua.VariantType.String),
            ("SigmaTranslationMm", 0.0, ua.VariantType.Double),
            ("SigmaRotationDeg", 0.0, ua.VariantType.Double),
            ("ProcessingMs", 0.0, ua.VariantType.Double),
            ("CreationTime", datetime.now(UTC), ua.VariantType.DateTime),
            *((node, default, vt) for node, _, default, vt in v.shown_fields()),
        ]

    # ------------------------------------------------------------------ states
    async def _show_states(self) -> None:
        if self.state == "Operational":
            self.auto_state = ("ContinuousExecution" if self._continuous is not None else
                               "SingleExecution" if self.jobs else
                               "Ready" if self.handler.selected_recipe() else "Initialized")
        for key, state in (("sm_state", self.state), ("auto_state", self.auto_state)):
            node = self._nodes[key]
            active = key == "sm_state" or self.state == "Operational"
            text = state if active else ""
            await node.write_value(ua.LocalizedText(text))
            await (await node.get_child("0:Id")).write_value(
                self._state_ids[state] if active else ua.NodeId())
        await self._nodes["system_state"].write_value(
            ua.Variant(v.system_state(self.state, self.auto_state)))

    async def _selected(self) -> RecipeInfo | None:
        return next((r for r in await self.handler.recipes() if r.selected), None)

    async def _show_recipe(self) -> None:
        number = self.handler.selected_recipe()
        current = await self._selected()
        name, version = (current.name, current.version) if current else ("", 0)
        n = self._nodes
        await n["recipe.Number"].write_value(ua.Variant(number, ua.VariantType.UInt16))
        await n["recipe.Name"].write_value(ua.Variant(name, ua.VariantType.String))
        await n["recipe.Version"].write_value(ua.Variant(version, ua.VariantType.UInt32))
        await n["recipe.Convention"].write_value(
            ua.Variant(self.handler.convention().value if number else "", ua.VariantType.String))
        if self.server is not None:
            await self._show_states()

    # ------------------------------------------------------------------ methods
    async def _halt(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        self.state = "Halted"
        await self._end_continuous()
        await self._show_states()
        return [v.int32(0)]

    async def _reset(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        await self._end_continuous()
        await self.handler.reset()
        self.state = "Operational"
        await self._show_states()
        return [v.int32(0)]

    async def _select_auto(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        if self.state == "Halted":
            return [v.int32(int(Reason.BUSY))]
        self.state = "Operational"  # automatic is the station's only mode
        await self._show_states()
        return [v.int32(0)]

    async def _prepare_recipe(self, parent: ua.NodeId, external: ua.Variant,
                              internal: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        wanted = v.struct_id(external.Value) or v.struct_id(internal.Value)
        code = int(Reason.BAD_ARGUMENT)
        if wanted.isdigit() and 0 < int(wanted) <= 65535:
            code = await self.handler.select_recipe(int(wanted))
        if code == 0:
            await self._show_recipe()
        current = await self._selected()
        out = (v.recipe_id("RecipeIdInternalDataType", current.name, current.version,
                           current.sha256, current.number)
               if current else _UA.RecipeIdInternalDataType(Id=""))
        return [ua.Variant(out), ua.Variant(code == 0, ua.VariantType.Boolean), v.int32(code)]

    async def _start_single_job(self, parent: ua.NodeId, meas: ua.Variant, part: ua.Variant,
                                recipe: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        number = v.struct_id(recipe.Value)
        if self.state != "Operational" or self._continuous is not None:
            return [ua.Variant(_UA.JobIdDataType(Id="")), v.int32(int(Reason.BUSY))]
        if number and not number.isdigit():
            return [ua.Variant(_UA.JobIdDataType(Id="")), v.int32(int(Reason.BAD_ARGUMENT))]
        trigger_id = self._next_trigger(v.struct_id(meas.Value))
        req = self._request(trigger_id, v.struct_id(part.Value), int(number or 0))
        self._spawn(self._job(req))
        return [ua.Variant(_UA.JobIdDataType(Id=str(trigger_id))), v.int32(0)]

    # ------------------------------------------------------------------ continuous mode
    async def _start_continuous(self, parent: ua.NodeId, meas: ua.Variant, part: ua.Variant,
                                recipe: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        """Triggers back to back until Stop, Abort, Halt or Reset: each one a normal trigger
        (its record, its event), the next one asked for once the station has answered the
        last, so a trigger of another link (Modbus) waits for one job at most."""
        none = ua.Variant(_UA.JobIdDataType(Id=""))
        number = v.struct_id(recipe.Value)
        if self.state != "Operational" or self._continuous is not None or self.jobs:
            return [none, v.int32(int(Reason.BUSY))]
        if number and not number.isdigit():
            return [none, v.int32(int(Reason.BAD_ARGUMENT))]
        known = {r.number for r in await self.handler.recipes()}
        if (int(number) not in known) if number else not self.handler.selected_recipe():
            # refused here rather than recorded over and over as UNKNOWN_RECIPE
            self._error(f"StartContinuous: no recipe {number or '(none selected)'}")
            return [none, v.int32(int(Reason.UNKNOWN_RECIPE))]
        first = self._next_trigger(v.struct_id(meas.Value))
        self._stop_requested = False
        self._continuous = self._spawn(
            self._run_continuous(first, v.struct_id(part.Value), int(number or 0)))
        await self._show_states()
        return [ua.Variant(_UA.JobIdDataType(Id=str(first))), v.int32(0)]

    async def _run_continuous(self, first: int, part_id: str, recipe: int) -> None:
        trigger_id = first
        try:
            while not self._stop_requested and self.state == "Operational":
                # its own task, shielded: Abort ends the loop, never a job inside the station
                job = self._spawn(self._job(self._request(trigger_id, part_id, recipe),
                                            single=False))
                out = await asyncio.shield(job)
                if out.result_code >= 1000:  # the link's own range: the station did not answer
                    self._error(f"continuous mode ended: trigger {trigger_id} was answered "
                                f"{reason_name(out.result_code)} by the link itself")
                    break
                trigger_id = self._next_trigger("")
        finally:
            self._continuous = None
            if self.server is not None:
                await self._show_states()

    async def _stop_continuous(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        """The running job ends with its record; then Ready (the call returns then)."""
        task = self._continuous
        if task is None:
            return [v.int32(int(Reason.BAD_ARGUMENT))]  # nothing runs
        self._stop_requested = True
        await asyncio.wait({task})  # a failed loop is logged by _spawn's callback
        return [v.int32(0)]

    async def _abort(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        """Ready at once; a half-done multi-view sequence is dropped (as Reset); a job already
        in the station still ends with its record and event."""
        if self._continuous is None:
            return [v.int32(int(Reason.BAD_ARGUMENT))]
        await self._end_continuous()
        await self.handler.reset()
        await self._show_states()
        return [v.int32(0)]

    async def _end_continuous(self) -> None:
        task = self._continuous
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    async def _measure(self, parent: ua.NodeId, part: ua.Variant, recipe: ua.Variant,
                       trigger: ua.Variant) -> list[ua.Variant]:
        if self.state != "Operational":
            out = LinkOutcome(int(Reason.BUSY), 0)
        else:
            req = self._request(self._next_trigger(str(trigger.Value or "")), str(part.Value or ""),
                                int(recipe.Value or 0))
            # shielded: a client that goes away mid-measurement does not cancel the record
            out = await asyncio.shield(self._spawn(self._job(req)))
        offset = list(out.offset) if out.offset is not None else []
        return [ua.Variant(out.result_id, ua.VariantType.UInt32), v.int32(out.result_code),
                ua.Variant(offset, ua.VariantType.Double),
                ua.Variant(out.sigma_trans_mm, ua.VariantType.Double),
                ua.Variant(out.sigma_rot_deg, ua.VariantType.Double)]

    async def _verify(self, parent: ua.NodeId) -> list[ua.Variant]:
        """mvpose's Verify: the taught reference part measured now and judged (ResultCode 0:
        judged, Passed is the verdict; else why there is no verdict)."""
        if self.state != "Operational":
            out = VerifyOutcome(int(Reason.BUSY), 0, message=f"the vision system is {self.state}")
        else:
            limit = self.config.measure_timeout_s
            try:  # shielded: a client that goes away mid-verify does not cancel the record
                out = await asyncio.shield(self._spawn(asyncio.wait_for(
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

    def _next_trigger(self, wanted: str) -> int:
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
        await self._show_states()
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
            self._error(f"trigger {req.trigger_id}: {text}")
            ms = (time.monotonic() - t0) * 1e3
            rid = await self.handler.record_failure(req, code, text, ms)
            return LinkOutcome(code, rid, processing_ms=ms)
        finally:
            self.jobs -= single
            if self.server is not None:
                await self._show_states()

    # ------------------------------------------------------------------ results
    def _on_result(self, event: ResultEvent) -> None:
        """The station's listener (on the station loop): publish on our loop."""
        loop = self._loop
        if self._listening and loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(lambda: self._spawn(self._publish(event)))

    async def _publish(self, r: ResultEvent) -> None:
        if self.server is None or self._evgen is None:
            return
        own, standard = v.result_fields(r, self.management.versions)
        async with self._lock:
            server = self.server
            for name, value in own.items():  # the server's own write: no session
                await server.write_attribute_value(self._nodes[f"last.{name}"].nodeid,
                                                   ua.DataValue(value))
            ev = self._evgen.event
            for name, value in {**own, **standard}.items():  # the standard's PartId, CreationTime
                ev.add_property(name, value.Value, value.VariantType)
            ev.Severity = 100 if standard["ResultState"].Value == v.RESULT_STATE_COMPLETED else 500
            ev.emitting_node = self._nodes["vs"].nodeid
            text = f"result {own['ResultNumber'].Value}: {own['Reason'].Value}"
            await self._evgen.trigger(time_attr=standard["CreationTime"].Value, message=text)
            # the same event through the Server object, the root of the notifier hierarchy
            ev.emitting_node = server.nodes.server.nodeid
            await server.iserver.subscription_service.trigger_event(ev)
            self.results += 1

    # ------------------------------------------------------------------ helpers
    def _spawn(self, coro: Any) -> asyncio.Future[Any]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)

        def done(t: asyncio.Future[Any]) -> None:
            self._tasks.discard(t)
            if not t.cancelled() and (err := t.exception()) is not None:
                log.error("OPC UA link task failed: %r", err, exc_info=err)
                self._error(f"{type(err).__name__}: {err}")

        task.add_done_callback(done)
        return task

    def _error(self, text: str) -> None:
        self.last_errors = [*self.last_errors[-19:], text]


async def _not_implemented(server: Server, root: Node) -> None:
    """The model's optional methods mvpose does not implement (AddRecipe, ConfirmAll,
    SimulationMode ...) answer BadNotImplemented (asyncua would say BadNothingToDo)."""

    async def refuse(parent: ua.NodeId, *args: ua.Variant) -> ua.StatusCode:
        return _UA.StatusCode(ua.StatusCodes.BadNotImplemented)

    space = server.iserver.aspace
    todo = [root]
    while todo:
        node = todo.pop()
        for child in await node.get_children(refs=ua.ObjectIds.HierarchicalReferences):
            cls = await child.read_node_class()
            if cls == ua.NodeClass.Method:
                if space[child.nodeid].call is None:
                    server.link_method(child, refuse)
            elif cls == ua.NodeClass.Object:
                todo.append(child)
