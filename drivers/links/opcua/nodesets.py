"""The Machine Vision information model: the OPC Foundation's NodeSet2 files, pinned and checked.

The files come from the npm package ``node-opcua-nodesets`` (pinned by
``opcua_nodesets/package-lock.json``) and are checked against ``opcua_nodesets/SHA256SUMS``
before they are imported: nothing of the model is typed in here.
"""

from __future__ import annotations

import hashlib
import time
import xml.etree.ElementTree as ET
from pathlib import Path

from asyncua import Server

NODESET_DIR = Path(__file__).resolve().parent.parent / "opcua_nodesets"
NODESET_FILES = NODESET_DIR / "node_modules" / "node-opcua-nodesets" / "nodesets"
MACHINE_VISION = "Opc.Ua.MachineVision.NodeSet2.xml"
MODEL_FILES = {  # ModelUri -> the NodeSet2 file that defines it
    "http://opcfoundation.org/UA/MachineVision": MACHINE_VISION,
    "http://opcfoundation.org/UA/DI/": "Opc.Ua.Di.NodeSet2.xml",
}
MV_URI = "http://opcfoundation.org/UA/MachineVision"
MVPOSE_URI = "urn:mvpose:opcua"  # mvpose's own nodes: our event subtype, Measure, LastResult
UA_NS = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"


class NodeSetError(RuntimeError):
    """A NodeSet2 file is missing or is not the pinned one."""


def _pinned() -> dict[str, str]:
    """File name -> sha256 from SHA256SUMS (``sha256sum -c`` format)."""
    sums = NODESET_DIR / "SHA256SUMS"
    out: dict[str, str] = {}
    for line in sums.read_text().splitlines():
        if line.strip():
            digest, _, rel = line.partition("  ")
            out[Path(rel).name] = digest
    return out


def nodeset_path(name: str, folder: Path = NODESET_FILES) -> Path:
    """``name`` from the npm package (``folder``), verified against the pinned sha256."""
    path = folder / name
    pinned = _pinned().get(name)
    if pinned is None:
        raise NodeSetError(f"{name} has no pinned hash in {NODESET_DIR / 'SHA256SUMS'}")
    if not path.is_file():
        raise NodeSetError(
            f"{path} is missing: install the NodeSets with `npm ci --prefix {NODESET_DIR}` "
            "(make venv does)")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != pinned:
        raise NodeSetError(f"{path}: sha256 {digest} is not the pinned {pinned} (SHA256SUMS)")
    return path


def required_models(path: Path) -> list[str]:
    """The ModelUris a NodeSet2 file says it needs (its <RequiredModel> elements)."""
    root = ET.parse(path).getroot()
    return [req.get("ModelUri", "") for req in root.iter(f"{UA_NS}RequiredModel")]


def import_order(model: str = MV_URI) -> list[Path]:
    """The NodeSet2 files to import for ``model``, each after the models it requires (the
    base namespace is built into asyncua)."""
    order: list[Path] = []

    def visit(uri: str) -> None:
        if uri not in MODEL_FILES:
            if uri.rstrip("/") != "http://opcfoundation.org/UA":
                raise NodeSetError(f"model {uri} is required but no NodeSet2 file provides it")
            return
        path = nodeset_path(MODEL_FILES[uri])
        for dep in required_models(path):
            visit(dep)
        if path not in order:
            order.append(path)

    visit(model)
    return order



async def load_times() -> dict[str, float]:
    """Seconds to build asyncua's base address space and to import the pinned NodeSets: what
    every start of the link costs (``python -m drivers.links.opcua``)."""
    t = time.monotonic()
    server = Server()
    await server.init()
    out = {"init": time.monotonic() - t}
    for path in import_order():
        t = time.monotonic()
        await server.import_xml(str(path))
        out[path.name] = time.monotonic() - t
    return out

