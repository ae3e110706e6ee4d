"""The OPC UA link in the real station (server.loopback, in-process): a station file whose links
section enables OPC UA next to Modbus; asyncua's Client triggers by method call and subscribes
to ResultReadyEvent; every event's ResultId is the stored record's seq, whichever link caused it.
"""

from __future__ import annotations

import asyncio
import socket
from pathlib import Path
from typing import Any

from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from stations import runtime_options, settings_for, station_file

from drivers.links.opcua import MV_URI, MVPOSE_URI, OpcUaLink
from mvpose_core.linkconfig import hash_password
from server.loopback import running_server
from server.store.schemas import MeasurementFilter

CLIENT_URI = "urn:mvpose:test:station-client"


class _Events:
    def __init__(self) -> None:
        self.queue: asyncio.Queue[Any] = asyncio.Queue()

    def event_notification(self, event: Any) -> None:
        self.queue.put_nowait(event)

    async def next(self) -> Any:
        return await asyncio.wait_for(self.queue.get(), 15)


async def test_opcua_triggers_and_publishes_the_stations_records(tmp_path: Path) -> None:
    pki = tmp_path / "pki"
    key, cert = tmp_path / "client.pem", tmp_path / "client.der"
    await setup_self_signed_certificate(key, cert, CLIENT_URI, socket.gethostname(),
                                        [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "t"})
    (pki / "trusted").mkdir(parents=True)
    (pki / "trusted" / "client.der").write_bytes(cert.read_bytes())

    def opcua(data: dict[str, Any]) -> None:
        data.setdefault("links", {})["opcua"] = {
            "port": 0, "pki_dir": str(pki), "security": ["Basic256Sha256_SignAndEncrypt"],
            "users": {"olga": {"role": "operator",
                               "password_hash": hash_password("pw", 10_000)}}}

    settings = settings_for(station_file(tmp_path, "station1", opcua), tmp_path / "var")
    async with running_server(settings, runtime_options(), http_port=None) as lb:
        station = lb.runtime
        link = next(lk for lk in station.links if isinstance(lk, OpcUaLink))
        # the Machine Vision NodeSet loads in the background of the station's start
        assert await asyncio.to_thread(link.started.wait, 120), link.status()
        assert {lk.name for lk in station.links} == {"modbus", "opcua"}
        assert station.status()["links"]["opcua"]["running"]
        client = Client(f"opc.tcp://127.0.0.1:{link.port}/mvpose", timeout=15)
        client.application_uri = CLIENT_URI
        await client.set_security(SecurityPolicyBasic256Sha256, certificate=str(cert),
                                  private_key=str(key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        client.set_user("olga")
        client.set_password("pw")
        await client.connect()
        try:
            await client.load_data_type_definitions()
            mv = await client.get_namespace_index(MV_URI)
            own = await client.get_namespace_index(MVPOSE_URI)
            vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
            name = await vs.get_child([f"{mv}:RecipeManagement", f"{own}:ActiveRecipe",
                                       f"{own}:Name"])
            assert await name.read_value() == station.active.config.name
            etype = await client.nodes.base_event_type.get_child(
                [f"{mv}:ResultReadyEventType", f"{own}:MvposeResultReadyEventType"])
            events = _Events()
            sub = await client.create_subscription(50, events)
            await sub.subscribe_events(vs, etype)

            rid, code, offset, s_mm, s_deg = await vs.call_method(
                f"{own}:Measure", ua.Variant("VIN-OPCUA", ua.VariantType.String),
                ua.Variant(0, ua.VariantType.UInt16), ua.Variant(31, ua.VariantType.UInt32))
            ev = await events.next()
            # a trigger through another link (the control channel's, as REST) is published too
            other = await asyncio.to_thread(station.trigger, "VIN-REST", 0, 32)
            ev2 = await events.next()
            station.wait_idle()
            recs = {r.seq: r.record for r in
                    station.services.store.measurements.iterate(MeasurementFilter())}
            assert rid in recs and other.outcome.result_id in recs
            rec = recs[rid]
            assert (rec.trigger_id, rec.part_id, rec.reason_code) == (31, "VIN-OPCUA", code)
            assert (ev.ResultId.Id, ev.ResultCode, ev.PartId.Id) == (str(rid), code, "VIN-OPCUA")
            if code == 0:
                assert offset == list(rec.offset.values) and s_mm > 0
                assert ev.Offset == offset and ev.Convention == rec.offset.convention.value
            assert (ev2.ResultId.Id, ev2.TriggerId, ev2.PartId.Id) == (
                str(other.outcome.result_id), 32, "VIN-REST")
            assert events.queue.empty()
        finally:
            await client.disconnect()
