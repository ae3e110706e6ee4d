"""Station alarms as OPC 40100 Machine Vision condition events (OPC 40100-1 §11.4).

The companion specification models a vision system's errors and warnings as conditions of
``VisionConditionType`` (a subtype of Part 9's ``AcknowledgeableConditionType``):
``VisionErrorConditionType`` for errors and ``VisionWarningConditionType`` for warnings, with the
error's ``ErrorCode`` (UInt64) and ``ErrorString``. Each transition of a station alarm
(raised, acknowledged, cleared) is one event of the type its priority maps to (high: error;
medium and low: warning), emitted by the VisionSystem and the Server object, carrying the
condition's state as Part 9 names it: ``ConditionName`` (the alarm's code), ``SourceName`` (its
source), ``EnabledState/Id`` true, ``AckedState/Id``, ``Retain`` (true while active or not
acknowledged), ``Severity`` (high 800, medium 500, low 300) and ``Message`` (the alarm's text).
``ConditionId`` ... a condition's node of its own, ConditionRefresh and the Acknowledge method
are not offered: acknowledge on the operator page or over REST (docs/alarms.md).
"""

from __future__ import annotations

import logging
from typing import Any

from asyncua import Node, Server, ua

from ..base import AlarmNotice

log = logging.getLogger(__name__)

_UA: Any = ua
SEVERITY = {"high": 800, "medium": 500, "low": 300}
#: the alarm's priority -> the companion specification's condition type
CONDITION_TYPE = {"high": "VisionErrorConditionType", "medium": "VisionWarningConditionType",
                  "low": "VisionWarningConditionType"}


class AlarmConditions:
    """The event generators of the station's alarms on one server."""

    def __init__(self) -> None:
        self._gens: dict[str, Any] = {}
        self._vs: Node | None = None
        self.sent = 0

    async def build(self, server: Server, vs: Node, mv: int) -> None:
        base = server.nodes.base_event_type
        for name in sorted(set(CONDITION_TYPE.values())):
            etype = await base.get_child(["0:ConditionType", "0:AcknowledgeableConditionType",
                                          f"{mv}:VisionConditionType", f"{mv}:{name}"])
            self._gens[name] = await server.get_event_generator(etype, vs.nodeid)
        self._vs = vs

    async def publish(self, server: Server, notice: AlarmNotice) -> None:
        if self._vs is None:
            return
        gen = self._gens[CONDITION_TYPE.get(notice.priority, "VisionWarningConditionType")]
        ev = gen.event
        values: dict[str, tuple[Any, ua.VariantType]] = {
            "ConditionName": (notice.code, ua.VariantType.String),
            "SourceName": (notice.source, ua.VariantType.String),
            "ErrorCode": (notice.alarm_id, ua.VariantType.UInt64),
            "ErrorString": (notice.text, ua.VariantType.String),
            "Retain": (notice.active or not notice.acknowledged, ua.VariantType.Boolean),
            "EnabledState": (_UA.LocalizedText("Enabled"), ua.VariantType.LocalizedText),
            "EnabledState/Id": (True, ua.VariantType.Boolean),
            "AckedState": (_UA.LocalizedText(
                "Acknowledged" if notice.acknowledged else "Unacknowledged"),
                ua.VariantType.LocalizedText),
            "AckedState/Id": (notice.acknowledged, ua.VariantType.Boolean),
            "ClientUserId": (notice.acked_by or "", ua.VariantType.String),
            "Comment": (_UA.LocalizedText(notice.event), ua.VariantType.LocalizedText),
        }
        for name, (value, vt) in values.items():
            ev.add_property(name, value, vt)
        ev.Severity = SEVERITY.get(notice.priority, 300)
        ev.emitting_node = self._vs.nodeid
        await gen.trigger(time_attr=notice.at, message=notice.text)
        # the same event through the Server object, the root of the notifier hierarchy
        ev.emitting_node = server.nodes.server.nodeid
        await server.iserver.subscription_service.trigger_event(ev)
        self.sent += 1
