"""The OPC UA backend of the link seam: a Machine Vision server (OPC 40100-1) with asyncua.

- :mod:`.nodesets`: the OPC Foundation's NodeSet2 files (npm, pinned, hash-checked);
- :mod:`.access`: users and roles; channels of unlisted security (None) kept to discovery;
- :mod:`.link`: :class:`OpcUaLink`, the server with the station's ``VisionSystem`` object, its
  state machines, triggers (single and continuous) and result events;
- :mod:`.management`: result, recipe and configuration management methods;
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
    "POLICIES": ".link", "OpcUaLink": ".link",
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
