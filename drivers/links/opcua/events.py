"""Event filters as OPC 10000-4 has them: ``OfType`` matches the type and its subtypes.

asyncua 2.1 evaluates a where clause's ``OfType`` as equality with the event's EventType
(``WhereClauseEvaluator``), so a standard client's filter ``OfType ResultReadyEventType`` (or
``OfType BaseEventType``) misses every event of a subtype: OPC 10000-4 §7.7.3 says OfType is true
for "the type or any subtype". asyncua's own client hides it: it lists every subtype in an
``InList``. The link's server gives each event monitored item an evaluator that reads the type
hierarchy of its address space; asyncua's installed files are not changed.
"""

from __future__ import annotations

from typing import Any

from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace
from asyncua.server.monitored_item_service import WhereClauseEvaluator

_UA: Any = ua  # asyncua's stubs are strict about a NodeId's identifier
_HAS_SUBTYPE = _UA.NodeId(ua.ObjectIds.HasSubtype)


class TypeHierarchy:
    """A type (ObjectType, DataType) and its supertypes (inverse HasSubtype), read from the
    address space once per type."""

    def __init__(self, aspace: AddressSpace) -> None:
        self._aspace = aspace
        self._known: dict[ua.NodeId, frozenset[ua.NodeId]] = {}

        self._chains: dict[ua.NodeId, tuple[ua.NodeId, ...]] = {}

    def chain(self, type_id: ua.NodeId) -> tuple[ua.NodeId, ...]:
        """``type_id``, its supertype, that one's, ... up to the root (types have one)."""
        known = self._chains.get(type_id)
        if known is None:
            found: list[ua.NodeId] = []
            current: ua.NodeId | None = type_id
            while current is not None and current not in found:
                found.append(current)
                node = self._aspace.get(current)
                current = next((ref.NodeId for ref in (node.references if node else [])
                                if ref.ReferenceTypeId == _HAS_SUBTYPE and not ref.IsForward),
                               None)
            known = self._chains[type_id] = tuple(found)
        return known

    def supertypes(self, type_id: ua.NodeId) -> frozenset[ua.NodeId]:
        """``type_id`` and every type it is a subtype of."""
        known = self._known.get(type_id)
        if known is None:
            known = self._known[type_id] = frozenset(self.chain(type_id))
        return known


class StandardWhereClause(WhereClauseEvaluator):
    """asyncua's where clause evaluation with OfType for the type or any subtype."""

    def __init__(self, plain: WhereClauseEvaluator, types: TypeHierarchy) -> None:
        super().__init__(plain.logger, plain._aspace, ua.ContentFilter(Elements=plain.elements))
        self._types = types

    def _eval_el(self, index: int, event: Any) -> Any:
        el = self.elements[index]
        if el.FilterOperator == ua.FilterOperator.OfType:
            wanted = self._eval_op(el.FilterOperands[0], event)
            return wanted in self._types.supertypes(event.EventType)
        return super()._eval_el(index, event)


def standard_event_filters(server: Server) -> None:
    """Every event monitored item created on ``server`` from now on evaluates its where clause
    with :class:`StandardWhereClause`."""
    service = server.iserver.subscription_service
    create = service.create_monitored_items
    types = TypeHierarchy(server.iserver.aspace)

    async def create_monitored_items(params: ua.CreateMonitoredItemsParameters
                                     ) -> list[ua.MonitoredItemCreateResult]:
        results = await create(params)
        sub = service.subscriptions.get(params.SubscriptionId)
        items = sub.monitored_item_srv._monitored_items if sub is not None else {}  # noqa: SLF001
        for result in results:
            item = items.get(result.MonitoredItemId) if result.StatusCode.is_good() else None
            plain = item.where_clause_evaluator if item is not None else None
            if item is not None and plain is not None:
                item.where_clause_evaluator = StandardWhereClause(plain, types)
        return results

    service.create_monitored_items = create_monitored_items  # type: ignore[method-assign]
