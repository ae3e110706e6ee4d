"""Links to the line's controllers behind one trigger interface (:mod:`drivers.links.base`).

Every backend is a folder ``drivers/links/<backend>/`` with its link class and its settings
model (the station file's ``links.<backend>`` block). ``BACKENDS`` and ``SETTINGS`` name each
backend's module and class; they are imported only when a station file names the backend, so a
station without OPC UA never imports asyncua. A backend in ``OWN_PROCESS`` runs in a child
process of the station (:mod:`drivers.links.process`): its per-result work (OPC UA) or its
per-poll work (Modbus/TCP: a PLC reads its status every few milliseconds) is pure Python and
would otherwise take the station process's GIL beside the trigger path; one in ``REALTIME``
keeps the station's real-time priority there (the PLC's handshake is the trigger path). A
backend in ``ON_BY_DEFAULT`` runs with its default settings when the station file does not
name it. A backend in ``CLIENTS`` connects to the PLC: its ``host`` and ``port`` are the PLC's
address.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ValidationError

from .base import Link, LinkOutcome, LinkRequest, StationHandler, relay

BACKENDS: dict[str, tuple[str, str]] = {
    "modbus": ("drivers.links.modbus", "ModbusLink"),
    "opcua": ("drivers.links.opcua", "OpcUaLink"),
    "enip": ("drivers.links.enip", "EnipLink"),
    "s7": ("drivers.links.s7", "S7Link"),
    "profinet": ("drivers.links.profinet", "ProfinetLink"),
}
SETTINGS: dict[str, tuple[str, str]] = {
    "modbus": ("drivers.links.modbus.settings", "ModbusLinkConfig"),
    "opcua": ("drivers.links.opcua.settings", "OpcUaLinkConfig"),
    "enip": ("drivers.links.enip.settings", "EnipLinkConfig"),
    "s7": ("drivers.links.s7.settings", "S7LinkConfig"),
    "profinet": ("drivers.links.profinet.settings", "ProfinetLinkConfig"),
}
OWN_PROCESS: frozenset[str] = frozenset({"opcua", "modbus"})
#: backends of OWN_PROCESS whose child runs at the station's real-time priority (the others at
#: the normal one)
REALTIME: frozenset[str] = frozenset({"modbus"})
#: backends that connect to the PLC (their host and port are the PLC's, not ours to listen on)
CLIENTS: frozenset[str] = frozenset({"s7"})
ON_BY_DEFAULT: tuple[str, ...] = ("modbus",)


class LinkSettingsError(ValueError):
    """A station file's ``links`` section does not fit the backends' settings models:
    ``problems`` holds (where, e.g. ``links.modbus.port``, what is wrong, the value)."""

    def __init__(self, problems: list[tuple[str, str, Any]]) -> None:
        super().__init__("; ".join(f"{where}: {msg} (value: {value!r})"
                                   for where, msg, value in problems))
        self.problems = problems


def _load(table: dict[str, tuple[str, str]], name: str) -> Any:
    try:
        module, cls = table[name]
    except KeyError:
        raise ValueError(f"unknown link backend {name!r}; known: {sorted(table)}") from None
    return getattr(importlib.import_module(module), cls)


def link_class(name: str) -> type[Link]:
    """The backend class for ``name`` (a key of BACKENDS)."""
    found: type[Link] = _load(BACKENDS, name)
    return found


def settings_model(name: str) -> type[BaseModel]:
    """The settings model of backend ``name`` (a key of SETTINGS)."""
    found: type[BaseModel] = _load(SETTINGS, name)
    return found


def link_settings(raw: Mapping[str, Any]) -> dict[str, BaseModel]:
    """Every backend's settings from a station file's ``links`` section (backend name → its
    block; a block that is null counts as absent), each validated by its backend's own model;
    the backends in ON_BY_DEFAULT with their defaults when absent. In BACKENDS order.
    LinkSettingsError names every unknown backend and every field that does not fit."""
    problems: list[tuple[str, str, Any]] = []
    for name in raw:
        if name not in SETTINGS:
            problems.append((f"links.{name}",
                             f"unknown link backend; known: {', '.join(SETTINGS)}", name))
    out: dict[str, BaseModel] = {}
    for name in SETTINGS:
        block = raw.get(name)
        if block is None and name not in ON_BY_DEFAULT:
            continue
        try:
            out[name] = settings_model(name).model_validate(block or {})
        except ValidationError as err:
            for e in err.errors():
                where = ".".join(["links", name, *(str(x) for x in e["loc"])])
                problems.append((where, e["msg"], e.get("input")))
    if problems:
        raise LinkSettingsError(problems)
    return out


def open_links(configs: Mapping[str, Any], handler: StationHandler) -> list[Link]:
    """One link per enabled backend config (``{name: config}``); not started yet. A backend in
    OWN_PROCESS is a :class:`~drivers.links.process.ProcessLink` here (the backend itself is
    imported only in its child process)."""
    from .process import hosted

    return [(hosted(name) if name in OWN_PROCESS else link_class(name))(cfg, handler)
            for name, cfg in configs.items() if getattr(cfg, "enabled", True)]


__all__ = ["BACKENDS", "CLIENTS", "ON_BY_DEFAULT", "OWN_PROCESS", "REALTIME", "SETTINGS", "Link",
           "LinkOutcome", "LinkRequest", "LinkSettingsError", "StationHandler", "link_class",
           "link_settings", "open_links", "relay", "settings_model"]
