"""The result as OPC UA shows it: the last result's variables (``ResultManagement/LastResult``)
and a ``ResultReadyEvent`` (our subtype ``MvposeResultReadyEventType``) for every recorded
answer whichever link or client caused it, ``ResultId`` = the record's seq, notified through
the VisionSystem and the Server object. The fields' values come from
:func:`.values.result_fields`; the nodes and the event generator are the address space's
(:mod:`.model`).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from asyncua import Server, ua

from . import values as v

if TYPE_CHECKING:
    from .model import Model



def result_fields() -> list[tuple[str, Any, ua.VariantType]]:
    """The last result's variables and the event's own fields: (name, initial value, type)."""
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


async def publish(server: Server, model: Model, own: dict[str, ua.Variant],
                  standard: dict[str, ua.Variant]) -> None:
    """One result (:func:`.values.result_fields`'s two parts): written to the last result's
    variables, then one event from the VisionSystem and the same from the Server object."""
    for name, value in own.items():  # the server's own write: no session
        await server.write_attribute_value(model.nodes[f"last.{name}"].nodeid,
                                           ua.DataValue(value))
    ev = model.evgen.event
    for name, value in {**own, **standard}.items():  # the standard's PartId, CreationTime
        ev.add_property(name, value.Value, value.VariantType)
    ev.Severity = 100 if standard["ResultState"].Value == v.RESULT_STATE_COMPLETED else 500
    ev.emitting_node = model.nodes["vs"].nodeid
    text = f"result {own['ResultNumber'].Value}: {own['Reason'].Value}"
    await model.evgen.trigger(time_attr=standard["CreationTime"].Value, message=text)
    # the same event through the Server object, the root of the notifier hierarchy
    ev.emitting_node = server.nodes.server.nodeid
    await server.iserver.subscription_service.trigger_event(ev)
