"""The VisionSystem's address space: the ``VisionSystem`` object (``VisionSystemType`` of the
OPC Foundation's Machine Vision NodeSet, :mod:`.nodesets`) built once on a server that has
imported the NodeSets, with the standard's methods linked to the state machines and jobs
(:mod:`.machine`) and the management objects (:mod:`.management`), mvpose's own nodes
(``RecipeManagement/ActiveRecipe``, ``ResultManagement/LastResult``, ``Measure``, ``Verify``,
the hand-eye methods of :mod:`.handeye`), the result event's subtype
``MvposeResultReadyEventType`` and the alarms' conditions (:mod:`.conditions`); the model's
optional methods mvpose does not implement answer BadNotImplemented.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from asyncua import Node, Server, ua

from . import values as v
from .access import Roles
from .arguments import check_arguments
from .conditions import AlarmConditions
from .events import standard_event_filters
from .handeye import HandEyeMethods
from .management import Management
from .nodesets import MV_URI, MVPOSE_URI
from .results import result_fields

if TYPE_CHECKING:
    from .machine import VisionMachine

_UA: Any = ua  # the NodeSet's structures are made at import time; asyncua's stubs are strict


@dataclass
class Model:
    """The nodes the link writes once the address space is built: ``nodes`` by key (``vs``,
    ``sm_state``, ``auto_state``, ``system_state``, ``recipe.<name>``, ``last.<name>``,
    ``measure``, ``verify`` ...), the state machines' states' node ids by state name, and the
    result event's generator."""

    nodes: dict[str, Node] = field(default_factory=dict)
    state_ids: dict[str, ua.NodeId] = field(default_factory=dict)
    evgen: Any = None


async def build(server: Server, model: Model, machine: VisionMachine, management: Management,
                roles: Roles, conditions: AlarmConditions) -> None:
    """The VisionSystem object from the Machine Vision NodeSet's type, its methods linked to
    ``machine`` and ``management``, mvpose's own nodes and event type added; the nodes the link
    writes go into ``model``."""
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
    n, m = model.nodes, machine
    n["vs"], n["sm"], n["auto"] = vs, sm, auto
    n["sm_state"] = await sm.get_child("0:CurrentState")
    n["system_state"] = await vs.get_child(f"{mv}:SystemState")
    n["auto_state"] = await auto.get_child("0:CurrentState")
    sm_type = server.get_node(v.typedef(await sm.read_type_definition()))
    auto_type = server.get_node(v.typedef(await auto.read_type_definition()))
    for state in ("Preoperational", "Halted", "Error", "Operational"):
        model.state_ids[state] = (await sm_type.get_child(f"{mv}:{state}")).nodeid
    for state in ("Initialized", "Ready", "SingleExecution", "ContinuousExecution"):
        model.state_ids[state] = (await auto_type.get_child(f"{mv}:{state}")).nodeid

    # methods of the standard: the state machines and PrepareRecipe here, the rest of the
    # management objects in .management
    links: dict[tuple[Node, str], Callable[..., Any]] = {
        (sm, "Halt"): m.halt, (sm, "Reset"): m.reset,
        (sm, "SelectModeAutomatic"): m.select_auto,
        (auto, "StartSingleJob"): m.start_single_job,
        (auto, "StartContinuous"): m.start_continuous,
        (auto, "Stop"): m.stop_continuous, (auto, "Abort"): m.abort,
        (rm, "PrepareRecipe"): m.prepare_recipe,
    }
    for (parent, method), fn in links.items():
        server.link_method(await parent.get_child(f"{mv}:{method}"), fn)
    await management.build(server, vs, mv)
    roles.engineer_methods = management.engineer_methods
    await not_implemented(server, vs)

    # mvpose's own: the active recipe, the last result, Measure, the event subtype
    recipe = await rm.add_object(idx, "ActiveRecipe")
    for name, value, vt in (("Number", 0, ua.VariantType.UInt16),
                            ("Name", "", ua.VariantType.String),
                            ("Version", 0, ua.VariantType.UInt32),
                            ("Convention", "", ua.VariantType.String)):
        n[f"recipe.{name}"] = await recipe.add_variable(idx, name, ua.Variant(value, vt))
    last = await res.add_object(idx, "LastResult")
    for name, value, vt in result_fields():
        n[f"last.{name}"] = await last.add_variable(idx, name, ua.Variant(value, vt))
    measure = await vs.add_method(
        idx, "Measure", m.measure,
        [v.arg("PartId", ua.ObjectIds.String), v.arg("RecipeNumber", ua.ObjectIds.UInt16),
         v.arg("TriggerId", ua.ObjectIds.UInt32)],
        [v.arg("ResultId", ua.ObjectIds.UInt32), v.arg("ResultCode", ua.ObjectIds.Int32),
         v.arg("Offset", ua.ObjectIds.Double, rank=1),
         v.arg("SigmaTranslationMm", ua.ObjectIds.Double),
         v.arg("SigmaRotationDeg", ua.ObjectIds.Double)])
    n["measure"] = measure
    n["verify"] = await vs.add_method(
        idx, "Verify", m.verify, [],
        [v.arg("ResultId", ua.ObjectIds.UInt32), v.arg("ResultCode", ua.ObjectIds.Int32),
         v.arg("Passed", ua.ObjectIds.Boolean),
         v.arg("Difference", ua.ObjectIds.Double, rank=1),
         v.arg("DisplacementMm", ua.ObjectIds.Double),
         v.arg("RotationDeg", ua.ObjectIds.Double), v.arg("Message", ua.ObjectIds.String)])
    handeye = HandEyeMethods(
        m.handler, lambda: None if m.state == "Operational"
        else f"the vision system is {m.state}", m.spawn,
        m.config.measure_timeout_s or 30.0)
    roles.engineer_methods.update(await handeye.add(vs, idx))
    rre = await types.get_child(["0:BaseEventType", f"{mv}:ResultReadyEventType"])
    props = [(name, vt) for name, _, vt in result_fields()
             if name not in ("PartId", "CreationTime")]
    etype = await server.create_custom_event_type(idx, "MvposeResultReadyEventType",
                                                  rre.nodeid, props)
    model.evgen = await server.get_event_generator(etype, vs.nodeid)
    await conditions.build(server, vs, mv)
    await check_arguments(server, vs)
    # the Server object notifies every event of the VisionSystem too (OPC 10000-3 §7.16:
    # the notifier hierarchy), and OfType filters match subtypes (.events)
    await server.nodes.server.add_reference(vs.nodeid, ua.ObjectIds.HasNotifier)
    standard_event_filters(server)


async def not_implemented(server: Server, root: Node) -> None:
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
