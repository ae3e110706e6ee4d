"""Links to the line's controllers behind one trigger interface (:mod:`drivers.links.base`).

``BACKENDS`` names each backend's module and class; they are imported only when a station file
enables them, so a station without OPC UA never imports asyncua. A backend in ``OWN_PROCESS`` runs
in a child process of the station (:mod:`drivers.links.process`): its per-result work is pure
Python and would otherwise hold the station process's GIL beside the trigger path.
"""

from __future__ import annotations

import importlib
from typing import Any

from .base import Link, LinkOutcome, LinkRequest, StationHandler, relay

BACKENDS: dict[str, tuple[str, str]] = {
    "modbus": ("drivers.links.modbus", "ModbusLink"),
    "opcua": ("drivers.links.opcua", "OpcUaLink"),
}
OWN_PROCESS: frozenset[str] = frozenset({"opcua"})


def link_class(name: str) -> type[Link]:
    """The backend class for ``name`` (a key of BACKENDS)."""
    try:
        module, cls = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown link backend {name!r}; known: {sorted(BACKENDS)}") from None
    found: type[Link] = getattr(importlib.import_module(module), cls)
    return found


def open_links(configs: dict[str, Any], handler: StationHandler) -> list[Link]:
    """One link per enabled backend config (``{name: config}``); not started yet. A backend in
    OWN_PROCESS is a :class:`~drivers.links.process.ProcessLink` here (the backend itself is
    imported only in its child process)."""
    from .process import hosted

    return [(hosted(name) if name in OWN_PROCESS else link_class(name))(cfg, handler)
            for name, cfg in configs.items() if getattr(cfg, "enabled", True)]


__all__ = ["BACKENDS", "OWN_PROCESS", "Link", "LinkOutcome", "LinkRequest", "StationHandler",
           "link_class", "open_links", "relay"]
