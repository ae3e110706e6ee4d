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

from asyncua import Server, ua
from asyncua.server.address_space import AttributeValue

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



async def complete_definitions(server: Server) -> list[str]:
    """Give the Machine Vision structure DataTypes that lack a DataTypeDefinition their
    parent's; returns their names.

    ``RecipeIdExternalDataType``, ``RecipeIdInternalDataType`` and ``ConfigurationIdDataType``
    are subtypes of ``BinaryIdBaseDataType`` that add no field, and the NodeSet (1.0.0) gives them
    no ``<Definition>``. OPC 10000-3 (1.04, §5.8.3) asks a server to expose the DataTypeDefinition
    attribute of every structure DataType; without it a client that builds its types from the
    server (asyncua's ``load_data_type_definitions``, FreeOpcUa/opcua-asyncio#1693) cannot decode
    ResultDataType, ConfigurationDataType or any other structure with such a field. The
    definition is the parent's fields with the subtype's own binary encoding.

    The server decodes them by that encoding too: each gets a class of its own in ``asyncua.ua``
    (the parent's fields), registered under its DataType and its binary encoding. Without it, a
    ``ConfigurationIdDataType`` a client sends (ActivateConfiguration, PrepareRecipe's external
    id) stays an undecoded ExtensionObject and reads as empty.
    """
    mv = await server.get_namespace_index(MV_URI)
    base = await server.nodes.base_structure_type.get_child([f"{mv}:BinaryIdBaseDataType"])
    parent = await base.read_data_type_definition()
    if not isinstance(parent, ua.StructureDefinition):
        raise NodeSetError(f"BinaryIdBaseDataType has no structure definition: {parent!r}")
    parent_class = ua.extension_objects_by_datatype.get(base.nodeid)
    if parent_class is None:
        raise NodeSetError("the importer made no class for BinaryIdBaseDataType")
    aspace = server.iserver.aspace
    done: list[str] = []
    for sub in await base.get_children(refs=ua.ObjectIds.HasSubtype):
        node = aspace.get(sub.nodeid)
        have = node.attributes.get(ua.AttributeIds.DataTypeDefinition) if node else None
        if node is None or (have is not None and have.value is not None
                            and have.value.Value is not None
                            and have.value.Value.Value is not None):
            continue  # it has one (the importer leaves an empty attribute where it has none)
        binary = [e for e in await sub.get_children(refs=ua.ObjectIds.HasEncoding)
                  if (await e.read_browse_name()).Name == "Default Binary"]
        if not binary:
            continue
        definition = ua.StructureDefinition(
            DefaultEncodingId=binary[0].nodeid, BaseDataType=base.nodeid,
            StructureType=parent.StructureType, Fields=list(parent.Fields))
        node.attributes[ua.AttributeIds.DataTypeDefinition] = AttributeValue(
            ua.DataValue(ua.Variant(definition)))
        name = (await sub.read_browse_name()).Name
        own = type(name, (parent_class,), {"__module__": parent_class.__module__,
                                           "data_type": sub.nodeid})
        ua.register_extension_object(name, binary[0].nodeid, own, sub.nodeid)
        setattr(ua, name, own)  # the importer bound the name to the parent's class
        done.append(name)
    return done


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

