"""The OPC UA backend of the link seam: a Machine Vision server (OPC 40100-1) with asyncua.

- :mod:`.nodesets`: the OPC Foundation's NodeSet2 files (npm, pinned, hash-checked);
- :mod:`.access`: users and roles; channels of unlisted security (None) kept to discovery;
- :mod:`.link`: :class:`OpcUaLink`, the server's life cycle and status, wiring the rooms below;
- :mod:`.endpoint`: the endpoint and its security policies, identity tokens, client certificates;
- :mod:`.model`: the address space: the ``VisionSystem`` object, its methods linked, mvpose's
  own nodes and result event type;
- :mod:`.machine`: the state machines, triggers (single and continuous), Measure and Verify;
- :mod:`.results`: the last result's variables and the result events;
- :mod:`.management`: result, recipe and configuration management methods;
- :mod:`.conditions`: the station's alarms as condition events;
- :mod:`.handeye`: the hand-eye methods; :mod:`.certificates`: the server's certificate;
- :mod:`.events`: OfType event filters that match subtypes (OPC 10000-4);
- :mod:`.arguments`: Call arguments checked against each method's InputArguments;
- :mod:`.values`: conversions between OPC UA values and the station's terms, the result
  event's fields;
- :mod:`.settings`: the station file's ``links.opcua`` block and the password hashes.

The names below are imported on first use, so the station process can validate ``links.opcua``
(:mod:`.settings`) without importing asyncua, which only the link's own process needs.

``python -m drivers.links.opcua`` prints what a start costs.
"""

from __future__ import annotations

import importlib
from typing import Any

_NAMES = {
    "POLICIES": ".endpoint", "OpcUaLink": ".link",
    "MACHINE_VISION": ".nodesets", "MV_URI": ".nodesets", "MVPOSE_URI": ".nodesets",
    "NodeSetError": ".nodesets", "import_order": ".nodesets", "load_times": ".nodesets",
    "nodeset_path": ".nodesets", "required_models": ".nodesets",
}


def __getattr__(name: str) -> Any:
    try:
        module = _NAMES[name]
    except KeyError:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    return getattr(importlib.import_module(module, __name__), name)


__all__ = sorted(_NAMES)
