"""An OPC 40100 client in a process of its own (asyncua's Client): decodes what the link sends.

A client in the test's own process never decodes anything by itself: the server there has put the
Machine Vision structures into ``asyncua.ua`` already. This one starts with nothing, loads the
types from the server as a plant's client does (``load_data_type_definitions``), calls the
management methods and prints what it decoded as JSON:

    python tests/drivers/opcua_client.py URL KEY CERT USER PASSWORD RESULT_ID

That works because the link gives the three Machine Vision id types the NodeSet leaves without a
DataTypeDefinition their parent's (drivers.links.opcua.nodesets.complete_definitions); without
it asyncua's client cannot build ResultDataType and the others (FreeOpcUa/opcua-asyncio#1693).
"""

from __future__ import annotations

import asyncio
import json
import sys
from typing import Any

from asyncua import Client, ua
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

MV_URI = "http://opcfoundation.org/UA/MachineVision"


async def main(url: str, key: str, cert: str, user: str, password: str,
               result_id: str) -> dict[str, Any]:
    client = Client(url, timeout=10, watchdog_intervall=10)
    client.application_uri = "urn:mvpose:test:client"
    await client.set_security(SecurityPolicyBasic256Sha256, certificate=cert, private_key=key,
                              mode=ua.MessageSecurityMode.SignAndEncrypt)
    client.set_user(user)
    client.set_password(password)
    await client.connect()
    try:
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
        # a ConfigurationIdDataType sent by this client: the server decodes it by its encoding
        _, by_version, by_version_err = await cm.call_method(
            f"{mv}:GetConfigurationById", ua.ConfigurationIdDataType(Id="", Version="1"),
            ua.Variant(0, ua.VariantType.Int32))
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
            "configuration_1": [by_version_err, by_version.InternalId.Id,
                                by_version.InternalId.Version],
            "recipes": [r.Id for r in out[3]],
        }
    finally:
        await client.disconnect()


if __name__ == "__main__":
    print(json.dumps(asyncio.run(main(*sys.argv[1:]))))
