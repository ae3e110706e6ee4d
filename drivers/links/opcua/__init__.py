"""The OPC UA backend of the link seam: a Machine Vision server (OPC 40100-1) with asyncua.

- :mod:`.nodesets`: the OPC Foundation's NodeSet2 files (npm, pinned, hash-checked);
- :mod:`.access`: users and roles; channels of unlisted security (None) kept to discovery;
- :mod:`.link`: :class:`OpcUaLink`, the server with the station's ``VisionSystem`` object, its
  state machines, triggers (single and continuous) and result events;
- :mod:`.management`: result, recipe and configuration management methods;
- :mod:`.events`: OfType event filters that match subtypes (OPC 10000-4);
- :mod:`.arguments`: Call arguments checked against each method's InputArguments;
- :mod:`.values`: conversions between OPC UA values and the station's terms, the result
  event's fields.

``python -m drivers.links.opcua`` prints what a start costs.
"""

from .link import POLICIES, OpcUaLink
from .nodesets import (
    MACHINE_VISION,
    MV_URI,
    MVPOSE_URI,
    NodeSetError,
    import_order,
    load_times,
    nodeset_path,
    required_models,
)

__all__ = ["MACHINE_VISION", "MVPOSE_URI", "MV_URI", "POLICIES", "NodeSetError", "OpcUaLink",
           "import_order", "load_times", "nodeset_path", "required_models"]
