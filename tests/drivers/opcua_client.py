"""An OPC 40100 client in a process of its own (asyncua's Client): decodes what the link sends.

A client in the test's own process never decodes anything by itself: the server there has put the
Machine Vision structures into ``asyncua.ua`` already. This one starts with nothing, loads the
types from the server as a plant's client does, calls the management methods and prints what it
decoded as JSON:

    python tests/drivers/opcua_client.py URL KEY CERT USER PASSWORD RESULT_ID [--no-workaround]

asyncua's ``load_data_type_definitions`` skips a structure DataType without a DataTypeDefinition
of its own, and then cannot build any structure with a field of that type. The Machine Vision
NodeSet (1.0.0) gives ``RecipeIdExternalDataType``, ``RecipeIdInternalDataType`` and
``ConfigurationIdDataType`` none: they are subtypes of ``BinaryIdBaseDataType`` that add no
field. So ResultDataType, ConfigurationDataType and others stay unknown to the client
(FreeOpcUa/opcua-asyncio#1693, open). :func:`load_machine_vision_types` works around it: each
such subtype gets its parent's fields, then the definitions are loaded again.
"""

from __future__ import annotations

import asyncio
import json
import sys
from typing import Any

from asyncua import Client, ua
from asyncua.common.structures104 import make_structure
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

MV_URI = "http://opcfoundation.org/UA/MachineVision"


async def load_machine_vision_types(client: Client) -> None:
    """``load_data_type_definitions``, with the subtypes it skips made from their parent."""
    await client.load_data_type_definitions()
    mv = await client.get_namespace_index(MV_URI)
    base = await client.nodes.base_structure_type.get_child([f"{mv}:BinaryIdBaseDataType"])
    for sub in await base.get_children(refs=ua.ObjectIds.HasSubtype):
        name = (await sub.read_browse_name()).Name
        if getattr(getattr(ua, name, None), "data_type", None) == sub.nodeid:
            continue  # loaded: the server gave it a definition
        sdef = await base.read_data_type_definition()
        encodings = await sub.get_children(refs=ua.ObjectIds.HasEncoding)
        binary = [e for e in encodings if (await e.read_browse_name()).Name == "Default Binary"]
        sdef.DefaultEncodingId = binary[0].nodeid
        sdef.BaseDataType = base.nodeid
        cls = make_structure(sub.nodeid, name, sdef)[name]
        cls.data_type = sub.nodeid  # type: ignore[attr-defined]
        ua.register_extension_object(name, binary[0].nodeid, cls, sub.nodeid)
    await client.load_data_type_definitions()


async def main(url: str, key: str, cert: str, user: str, password: str, result_id: str,
               workaround: bool) -> dict[str, Any]:
    client = Client(url, timeout=10)
    client.application_uri = "urn:mvpose:test:client"
    await client.set_security(SecurityPolicyBasic256Sha256, certificate=cert, private_key=key,
                              mode=ua.MessageSecurityMode.SignAndEncrypt)
    client.set_user(user)
    client.set_password(password)
    await client.connect()
    try:
        if workaround:
            await load_machine_vision_types(client)
        else:
            await client.load_data_type_definitions()
        known = {n: hasattr(ua, n) for n in ("ResultDataType", "ConfigurationDataType",
                                             "RecipeIdInternalDataType")}
        if not all(known.values()):
            return {"known": known}
        mv = await client.get_namespace_index(MV_URI)
        vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
        res = await vs.get_child(f"{mv}:ResultManagement")
        _, result, err = await res.call_method(
            f"{mv}:GetResultById", ua.ResultIdDataType(Id=result_id),
            ua.Variant(0, ua.VariantType.Int32))
        cm = await vs.get_child(f"{mv}:ConfigurationManagement")
        active = await (await cm.get_child(f"{mv}:ActiveConfiguration")).read_value()
        rm = await vs.get_child(f"{mv}:RecipeManagement")
        out = await rm.call_method(
            f"{mv}:GetRecipeListFiltered", ua.RecipeIdExternalDataType(Id=""),
            ua.ProductIdDataType(Id=""), ua.Variant(2, ua.VariantType.Int32),
            ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.UInt32),
            ua.Variant(0, ua.VariantType.Int32))
        return {
            "known": known, "error": err, "type": type(result).__name__,
            "result_id": result.ResultId.Id, "part_id": result.PartId.Id,
            "recipe": [result.InternalRecipeId.Id, result.InternalRecipeId.Version],
            "configuration": [result.InternalConfigurationId.Id,
                              result.InternalConfigurationId.Version],
            "state": result.ResultState,
            "content": [c.Value for c in result.ResultContent or []],
            "active_configuration": [active.InternalId.Id, active.InternalId.Version],
            "recipes": [r.Id for r in out[3]],
        }
    finally:
        await client.disconnect()


if __name__ == "__main__":
    args = sys.argv[1:]
    workaround = "--no-workaround" not in args
    args = [a for a in args if a != "--no-workaround"]
    print(json.dumps(asyncio.run(main(*args, workaround=workaround))))
