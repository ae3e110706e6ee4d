"""Links to the line's controllers behind one trigger interface (:mod:`drivers.links.base`).

``BACKENDS`` names each backend's module and class; they are imported only when a station file
enables them, so a station without OPC UA never imports asyncua.
"""

from __future__ import annotations

import importlib
from typing import Any

from .base import Link, LinkOutcome, LinkRequest, StationHandler, relay

BACKENDS: dict[str, tuple[str, str]] = {
    "modbus": ("drivers.links.modbus", "ModbusLink"),
    "opcua": ("drivers.links.opcua", "OpcUaLink"),
}


def link_class(name: str) -> type[Link]:
    """The backend class for ``name`` (a key of BACKENDS)."""
    try:
        module, cls = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown link backend {name!r}; known: {sorted(BACKENDS)}") from None
    found: type[Link] = getattr(importlib.import_module(module), cls)
    return found


def open_links(configs: dict[str, Any], handler: StationHandler) -> list[Link]:
    """One link per enabled backend config (``{name: config}``); not started yet."""
    return [link_class(name)(cfg, handler) for name, cfg in configs.items()
            if getattr(cfg, "enabled", True)]


__all__ = ["BACKENDS", "Link", "LinkOutcome", "LinkRequest", "StationHandler", "link_class",
           "open_links", "relay"]
