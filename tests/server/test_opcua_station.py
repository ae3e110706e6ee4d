"""The OPC UA link in the real station (server.loopback, in-process): a station file whose links
section enables OPC UA next to Modbus; asyncua's Client triggers by method call and subscribes
to ResultReadyEvent; every event's ResultId is the stored record's seq, whichever link caused it.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import node_opcua
import pytest
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from opcua_events import Events
from stations import relaxed_deadline, runtime_options, settings_for, station_file
from waiting import until

from drivers.links.layout import Status
from drivers.links.opcua import MV_URI, MVPOSE_URI
from drivers.links.opcua.settings import hash_password
from drivers.links.process import ProcessLink
from mvpose_core.reasons import Reason
from server.loopback import move_part, running_server, running_station, trigger
from server.store.alarms import AlarmFilter
from server.store.schemas import MeasurementFilter

CLIENT_URI = "urn:mvpose:test:station-client"


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
        link = _opcua_link(station)
        # the Machine Vision NodeSet loads in the background of the station's start
        assert await asyncio.to_thread(link.started.wait, 120), link.status()
        assert {lk.name for lk in station.links} == {"modbus", "opcua"}
        assert station.status()["links"]["opcua"]["running"]
        client = Client(f"opc.tcp://127.0.0.1:{link.port}/mvpose", timeout=15,
                        watchdog_intervall=15)
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
            events = Events()
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
            # the result event's SHOWN fields are event properties and LastResult variables:
            # the fit's residual, as recorded
            rms2 = recs[other.outcome.result_id].residuals
            assert ev.ResidualRmsPx == (rec.residuals.rms_px if rec.residuals else 0.0)
            assert ev2.ResidualRmsPx == (rms2.rms_px if rms2 else 0.0)
            last = await vs.get_child([f"{mv}:ResultManagement", f"{own}:LastResult",
                                       f"{own}:ResidualRmsPx"])
            # (written before the event is triggered)
            assert await last.read_value() == ev2.ResidualRmsPx
            assert events.queue.empty()
        finally:
            await client.disconnect()


def _opcua(pki: Path) -> Any:
    def edit(data: dict[str, Any]) -> None:
        data.setdefault("links", {})["opcua"] = {
            "port": 0, "pki_dir": str(pki), "security": ["Basic256Sha256_SignAndEncrypt"],
            "users": {"olga": {"role": "operator", "password_hash": hash_password("pw", 10_000)},
                      "erik": {"role": "engineer",
                               "password_hash": hash_password("pw", 10_000)}}}
    return edit


async def _trusted_certificate(tmp_path: Path) -> tuple[Path, Path]:
    """A client key and certificate (made once), the certificate trusted by the station."""
    key, cert = tmp_path / "client.pem", tmp_path / "client.der"
    if not cert.exists():
        await setup_self_signed_certificate(key, cert, CLIENT_URI, socket.gethostname(),
                                            [ExtendedKeyUsageOID.CLIENT_AUTH],
                                            {"commonName": "t"})
        trusted = tmp_path / "pki" / "trusted"
        trusted.mkdir(parents=True, exist_ok=True)
        (trusted / "client.der").write_bytes(cert.read_bytes())
    return key, cert


async def _client(link: ProcessLink, tmp_path: Path, user: str) -> Client:
    key, cert = await _trusted_certificate(tmp_path)
    client = Client(f"opc.tcp://127.0.0.1:{link.port}/mvpose", timeout=15, watchdog_intervall=15)
    client.application_uri = CLIENT_URI
    await client.set_security(SecurityPolicyBasic256Sha256, certificate=str(cert),
                              private_key=str(key), mode=ua.MessageSecurityMode.SignAndEncrypt)
    client.set_user(user)
    client.set_password("pw")
    await client.connect()
    await client.load_data_type_definitions()  # the station's server put them in ua already
    return client


def _opcua_link(station: Any) -> ProcessLink:
    """The station's side of its OPC UA link (the server runs in a child process)."""
    return next(lk for lk in station.links if isinstance(lk, ProcessLink) and lk.name == "opcua")


@contextlib.asynccontextmanager
async def _opcua_station(tmp_path: Path) -> AsyncIterator[tuple[Any, ProcessLink]]:
    """Station 1 in-process with its PLC twin and an OPC UA link that has started."""
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline,
                                         _opcua(tmp_path / "pki")), tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        link = _opcua_link(lb.runtime)
        assert await asyncio.to_thread(link.started.wait, 120), link.status()
        yield lb, link


async def test_results_by_id_are_the_stations_records_and_plc_triggers_interleave_with_continuous_mode(  # noqa: E501
        tmp_path: Path) -> None:
    async with _opcua_station(tmp_path) as (lb, link):
        station = lb.runtime
        recipe = station.active.config
        await move_part(station, lb.twin, recipe.T_rf_from_pf0.matrix)
        client = await _client(link, tmp_path, "olga")
        try:
            mv = await client.get_namespace_index(MV_URI)
            own = await client.get_namespace_index(MVPOSE_URI)
            vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
            res = await vs.get_child(f"{mv}:ResultManagement")
            auto = await vs.get_child([f"{mv}:VisionStateMachine",
                                       f"{mv}:AutomaticModeStateMachine"])

            # a PLC trigger over Modbus: its record, read over OPC UA by the same id
            status, _ = await trigger(lb.twin, recipe, 41, None, part_id="VIN-MB")
            station.wait_idle()
            store = station.services.store.measurements
            rec = next(iter(store.iterate(MeasurementFilter(result_id=status.result_id))))
            handle, result, err = await res.call_method(
                f"{mv}:GetResultById", ua.ResultIdDataType(Id=str(status.result_id)),
                ua.Variant(0, ua.VariantType.Int32))
            assert (handle, err) == (0, 0)
            assert (result.ResultId.Id, result.MeasId.Id, result.PartId.Id) == (
                str(rec.seq), "41", "VIN-MB")
            assert (result.InternalRecipeId.Id, result.InternalRecipeId.Version) == (
                rec.record.recipe, str(rec.record.recipe_version))
            code = rec.record.reason_code
            assert code == status.result_code
            assert result.ResultState == (1 if code == 0 else -code)
            if code == 0:
                unc = rec.record.uncertainty
                assert [c.Value for c in result.ResultContent] == [
                    *rec.record.offset.values, unc.sigma_mm, unc.sigma_deg]
            _, result, err = await res.call_method(
                f"{mv}:GetResultById", ua.ResultIdDataType(Id=str(rec.seq + 1000)),
                ua.Variant(0, ua.VariantType.Int32))
            assert (err, result.ResultId.Id) == (int(Reason.BAD_ARGUMENT), "")
            complete, count, _, items, err = await res.call_method(
                f"{mv}:GetResultListFiltered", ua.Variant(0, ua.VariantType.Int32),
                ua.MeasIdDataType(Id="41"), ua.PartIdDataType(Id=""),
                ua.RecipeIdExternalDataType(Id="1"), ua.RecipeIdInternalDataType(Id=""),
                ua.ConfigurationIdDataType(Id=""), ua.ConfigurationIdDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.JobIdDataType(Id=""),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.Int32))
            assert (err, complete, count, [r.ResultId.Id for r in items]) == (
                0, True, 1, [str(rec.seq)])

            # continuous mode; a PLC trigger meanwhile queues on the one trigger thread
            etype = await client.nodes.base_event_type.get_child(
                [f"{mv}:ResultReadyEventType", f"{own}:MvposeResultReadyEventType"])
            events = Events()
            sub = await client.create_subscription(20, events)
            await sub.subscribe_events(vs, etype)
            job, err = await auto.call_method(
                f"{mv}:StartContinuous", ua.MeasIdDataType(Id="9000"),
                ua.PartIdDataType(Id="VIN-CONT"), ua.RecipeIdExternalDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.Variant())
            assert (job.Id, err) == ("9000", 0)
            parts = [(await events.next()).PartId.Id for _ in range(2)]
            plc, _ = await trigger(lb.twin, recipe, 42, None, part_id="VIN-PLC")
            assert plc.result_id > 0  # answered while continuous mode runs
            while "VIN-PLC" not in parts or parts[-1] != "VIN-CONT":
                parts.append((await events.next()).PartId.Id)
            assert await auto.call_method(f"{mv}:Stop", ua.Variant(0, ua.VariantType.Int32),
                                          ua.Variant("", ua.VariantType.String)) == 0
            state = await (await auto.get_child("0:CurrentState")).read_value()
            assert state.Text == "Ready"
            station.wait_idle()
            rows = list(store.iterate(MeasurementFilter()))
            cont = [r.seq for r in rows if r.record.part_id == "VIN-CONT"]
            assert min(cont) < plc.result_id < max(cont)  # between two continuous jobs
            assert len(cont) >= 3 and len(set(cont)) == len(cont)
            assert [r.record.trigger_id for r in rows if r.seq == min(cont)] == [9000]
            # each continuous job has its record and its event (the last one's may still be
            # on its way: events go out with the subscription's publishing interval)
            while parts.count("VIN-CONT") < len(cont):
                parts.append((await events.next()).PartId.Id)
            assert parts.count("VIN-PLC") == 1
            complete, count, _, items, err = await res.call_method(
                f"{mv}:GetResultListFiltered", ua.Variant(0, ua.VariantType.Int32),
                ua.MeasIdDataType(Id=""), ua.PartIdDataType(Id="VIN-CONT"),
                ua.RecipeIdExternalDataType(Id=""), ua.RecipeIdInternalDataType(Id=""),
                ua.ConfigurationIdDataType(Id=""), ua.ConfigurationIdDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.JobIdDataType(Id=""),
                ua.Variant(2, ua.VariantType.UInt32), ua.Variant(1, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.Int32))
            assert (err, count, complete) == (0, 2, len(cont) <= 3)
            assert [int(r.ResultId.Id) for r in items] == cont[1:3]
        finally:
            await client.disconnect()


async def test_unprepare_and_the_calibration_versions_go_through_the_station(
        tmp_path: Path) -> None:
    from mvpose_core.calibration.files import CameraCalibration, InputsSummary, make_calibration

    async with _opcua_station(tmp_path) as (lb, link):
        station = lb.runtime
        recipe = station.active.config
        cam = station.station.camera("top_left").model
        calibs = [make_calibration("intrinsics", InputsSummary(board="test"), station="station1",
                                   cameras={"top_left": CameraCalibration(
                                       intrinsics={"fx": cam.fx + d, "fy": cam.fy,
                                                   "cx": cam.cx, "cy": cam.cy},
                                       distortion=list(cam.dist),
                                       image_size=(cam.width, cam.height))})
                  for d in (1.0, 2.0)]
        versions = station.services.store.versions
        edited = calibs[0].model_dump(mode="json")
        edited["cameras"]["top_left"]["intrinsics"]["fx"] += 5.0  # no longer its sha256
        for content in [c.model_dump(mode="json") for c in calibs] + [edited]:
            versions.add("calibration", "station1", content, "test", comment="stored")
        engineer = await _client(link, tmp_path, "erik")
        operator = await _client(link, tmp_path, "olga")
        try:
            mv = await engineer.get_namespace_index(MV_URI)
            vs = await engineer.nodes.objects.get_child(f"{mv}:VisionSystem")
            cm = await vs.get_child(f"{mv}:ConfigurationManagement")
            active = await cm.get_child(f"{mv}:ActiveConfiguration")
            assert (await active.read_value()).InternalId.Id == ""  # the station file has none
            complete, count, _, items, err = await cm.call_method(
                f"{mv}:GetConfigurationList", ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.Int32))
            assert (complete, count, err) == (True, 3, 0)
            assert [(c.InternalId.Id, c.InternalId.Version) for c in items] == [
                (calibs[0].id, "1"), (calibs[1].id, "2"), (calibs[0].id, "3")]
            assert items[1].InternalId.Hash == bytes.fromhex(calibs[1].sha256)

            assert await cm.call_method(f"{mv}:ActivateConfiguration",
                                        ua.ConfigurationIdDataType(Id="", Version="2")) == 0
            # measured with from the next trigger on, as after a REST activation
            assert station.station.camera("top_left").intrinsics.fx == cam.fx + 2.0
            assert station.status()["calibration"] == {
                "id": calibs[1].id, "sha256": calibs[1].sha256, "version": 2}
            shown = await active.read_value()
            assert (shown.InternalId.Id, shown.InternalId.Version) == (calibs[1].id, "2")
            # the edited version is refused with the REST upload's own check
            assert await cm.call_method(
                f"{mv}:ActivateConfiguration",
                ua.ConfigurationIdDataType(Id="", Version="3")) == int(Reason.BAD_ARGUMENT)
            # the child's status reaches the station within 0.2 s
            await until(lambda: "does not match its sha256" in " ".join(
                link.status()["last_errors"][-1:]), "the refusal in the link's status")
            assert station.status()["calibration"]["version"] == 2
            ovs = await operator.nodes.objects.get_child(f"{mv}:VisionSystem")
            ocm = await ovs.get_child(f"{mv}:ConfigurationManagement")
            with pytest.raises(ua.UaError, match="BadUserAccessDenied"):
                await ocm.call_method(f"{mv}:ActivateConfiguration",
                                      ua.ConfigurationIdDataType(Id="", Version="1"))
            assert station.status()["calibration"]["version"] == 2

            # the recipe: listed, unprepared (a trigger without recipe is refused), prepared
            rm = await ovs.get_child(f"{mv}:RecipeManagement")
            complete, count, _, items, err = await rm.call_method(
                f"{mv}:GetRecipeListFiltered", ua.RecipeIdExternalDataType(Id=""),
                ua.ProductIdDataType(Id=""), ua.Variant(1, ua.VariantType.Int32),
                ua.Variant(0, ua.VariantType.UInt32), ua.Variant(0, ua.VariantType.UInt32),
                ua.Variant(0, ua.VariantType.Int32))
            assert [(r.Id, r.Version) for r in items] == [
                (recipe.name, str(station.active.version))]
            out, err = await rm.call_method(
                f"{mv}:UnprepareRecipe", ua.RecipeIdExternalDataType(Id="1"),
                ua.RecipeIdInternalDataType(Id=""))
            assert (out.Id, err, station.active) == (recipe.name, 0, None)
            # the PLC sees what it sees without a recipe: INITIALIZED, no READY for triggers
            plc = await lb.twin.wait_for(lambda st: st.state.name == "INITIALIZED", 5,
                                         "INITIALIZED")
            assert not plc.has(Status.READY)
            # a trigger that names no recipe is refused and recorded
            own = await operator.get_namespace_index(MVPOSE_URI)
            rid, code, *_ = await ovs.call_method(
                f"{own}:Measure", ua.Variant("VIN-NONE", ua.VariantType.String),
                ua.Variant(0, ua.VariantType.UInt16), ua.Variant(51, ua.VariantType.UInt32))
            assert code == Reason.UNKNOWN_RECIPE and rid > 0
            station.wait_idle()
            refused = next(iter(station.services.store.measurements.iterate(
                MeasurementFilter(result_id=rid)))).record
            assert refused.message is not None and "no recipe is selected" in refused.message
            auto = await ovs.get_child([f"{mv}:VisionStateMachine",
                                        f"{mv}:AutomaticModeStateMachine", "0:CurrentState"])
            assert (await auto.read_value()).Text == "Initialized"
            _, done, err = await rm.call_method(
                f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id="1"),
                ua.RecipeIdInternalDataType(Id=""))
            assert (done, err, station.active.config.name) == (True, 0, recipe.name)
            status, _ = await trigger(lb.twin, recipe, 52, None)
            assert status.result_code != Reason.UNKNOWN_RECIPE
        finally:
            await engineer.disconnect()
            await operator.disconnect()


async def test_a_second_client_stack_gets_the_stations_records_as_standard_events(
        tmp_path: Path) -> None:
    """node-opcua (tests/node_opcua.py) subscribes as a generic OPC 40100 client does (OfType
    ResultReadyEventType, on the VisionSystem and on the Server object) and triggers; each event
    has every Mandatory field as the store has the record; SystemState is stand-by after."""
    async with _opcua_station(tmp_path) as (lb, link):
        station = lb.runtime
        await move_part(station, lb.twin, station.active.config.T_rf_from_pf0.matrix)
        key, cert = await _trusted_certificate(tmp_path)
        fields = ["EventType", "mv:ResultId", "mv:IsPartial", "mv:ResultState", "mv:JobId",
                  "mv:CreationTime", "mv:InternalRecipeId", "mv:InternalConfigurationId",
                  "mv:ProcessingTimes"]
        got = await node_opcua.run({
            "url": f"opc.tcp://127.0.0.1:{link.port}/mvpose", "mode": "SignAndEncrypt",
            "policy": "Basic256Sha256", "cert": str(cert), "key": str(key),
            "pki": str(tmp_path / "node-pki"), "applicationUri": CLIENT_URI, "user": "olga",
            "password": "pw", "steps": [
                *({"do": "subscribe", "label": label, "node": node, "fields": fields,
                   "ofType": ["mv:ResultReadyEventType"]}
                  for label, node in (("vs", ["mv:VisionSystem"]), ("server", "Server"))),
                {"do": "call", "object": ["mv:VisionSystem"], "method": "mvpose:Measure",
                 "args": [{"type": "String", "value": "VIN-NODE"},
                          {"type": "UInt16", "value": 0}, {"type": "UInt32", "value": 61}]},
                {"do": "wait_events", "label": "vs", "count": 1, "timeout_ms": 30000},
                {"do": "wait_events", "label": "server", "count": 1, "timeout_ms": 30000},
                {"do": "read", "path": ["mv:VisionSystem", "mv:SystemState"]}]})
        assert "error" not in got, got
        call, on_vs, on_server, state = got["results"][2:]
        rid = call["outputs"][0]
        station.wait_idle()
        rec = next(iter(station.services.store.measurements.iterate(
            MeasurementFilter(result_id=rid)))).record
        assert (len(on_vs), len(on_server)) == (1, 1), got
        ev = on_vs[0]
        assert on_server[0] == ev  # the same event through the Server object
        assert (ev["mv:ResultId"]["id"], ev["mv:JobId"]["id"]) == (str(rid), "61")
        assert ev["mv:IsPartial"] is False
        assert ev["mv:ResultState"] == (1 if rec.reason_code == 0 else -rec.reason_code)
        assert ev["mv:CreationTime"][:19] == rec.triggered_at.isoformat()[:19]
        assert (ev["mv:InternalRecipeId"]["id"], ev["mv:InternalRecipeId"]["version"]) == (
            rec.recipe, str(rec.recipe_version))
        assert ev["mv:InternalConfigurationId"]["id"] == ""  # the station file has none
        assert ev["mv:ProcessingTimes"]["startTime"] == ev["mv:CreationTime"]
        assert state["value"]["state"] == 2  # SBY_2 once the job is done


async def test_the_stations_alarms_are_condition_events(tmp_path: Path) -> None:
    """The station's alarm watch raises LINK_NO_PLC (its Modbus link has no PLC); the OPC UA
    link, in its own process, publishes it as OPC 40100's VisionErrorConditionType event, and
    an operator's acknowledgement (written by another process: the API's) follows. node-opcua,
    subscribed as a generic client (OfType VisionConditionType), gets NOK_STREAK (the recipe
    warns after one NOK here) raised by its own Measure call as a warning condition event."""
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

    def one_nok(data: dict[str, Any]) -> None:
        for recipe in data["recipes"]:
            recipe["nok_streak_warning"] = 1

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline, opcua, one_nok),
                            tmp_path / "var")
    async with running_server(settings, runtime_options(), http_port=None) as lb:
        station = lb.runtime
        link = _opcua_link(station)
        assert await asyncio.to_thread(link.started.wait, 120), link.status()
        client = Client(f"opc.tcp://127.0.0.1:{link.port}/mvpose", timeout=15,
                        watchdog_intervall=15)
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
            vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
            etype = await client.nodes.base_event_type.get_child(
                ["0:ConditionType", "0:AcknowledgeableConditionType",
                 f"{mv}:VisionConditionType"])
            events = Events(timeout_s=30)
            sub = await client.create_subscription(50, events)
            await sub.subscribe_events(vs, etype)
            alarms = station.services.store.alarms
            # raised by the watch after its on-delay (or before we subscribed: then acknowledge
            # it anyway, and the acknowledgement is the first event we see)
            await until(lambda: alarms.find(AlarmFilter(source="link:modbus")),
                        "LINK_NO_PLC in the store", 30)
            alarm = alarms.find(AlarmFilter(source="link:modbus"))[0]
            assert alarm.code == "LINK_NO_PLC"
            await asyncio.to_thread(alarms.acknowledge, alarm.id, "alice")
            seen = []
            while not seen or seen[-1].Comment.Text != "acknowledged":
                seen.append(await events.next())
            ev = seen[-1]
            assert (ev.ConditionName, ev.SourceName, ev.ErrorCode) == (
                "LINK_NO_PLC", "link:modbus", alarm.id)
            assert (ev.Severity, ev.Retain, ev.AckedState.Text, ev.ClientUserId) == (
                800, True, "Acknowledged", "alice")
            assert [e.Comment.Text for e in seen][-2:] in (["raised", "acknowledged"],
                                                           ["acknowledged"])
            await sub.delete()
        finally:
            await client.disconnect()

        # node-opcua: its Measure call (nothing in front of the cameras: NOK) raises NOK_STREAK
        got = await node_opcua.run({
            "url": f"opc.tcp://127.0.0.1:{link.port}/mvpose", "mode": "SignAndEncrypt",
            "policy": "Basic256Sha256", "cert": str(cert), "key": str(key),
            "pki": str(tmp_path / "node-pki"), "applicationUri": CLIENT_URI, "user": "olga",
            "password": "pw", "steps": [
                {"do": "subscribe", "label": "vs", "node": ["mv:VisionSystem"],
                 "fields": ["mv:ErrorCode", "mv:ErrorString", "ConditionName", "SourceName",
                            "Retain", "Severity"],
                 "ofType": ["ConditionType", "AcknowledgeableConditionType",
                            "mv:VisionConditionType"]},
                {"do": "call", "object": ["mv:VisionSystem"], "method": "mvpose:Measure",
                 "args": [{"type": "String", "value": "VIN-NOK"},
                          {"type": "UInt16", "value": 0}, {"type": "UInt32", "value": 71}]},
                {"do": "wait_events", "label": "vs", "count": 1, "timeout_ms": 30000}]})
        assert "error" not in got, got
        call, on_vs = got["results"][1:]
        assert call["outputs"][1] != 0, call  # NOK
        streak = alarms.find(AlarmFilter(source="station"))[0]
        # node-opcua reads a UInt64 as [high 32 bits, low 32 bits]
        assert on_vs == [{"mv:ErrorCode": [0, streak.id], "mv:ErrorString": streak.text,
                          "ConditionName": "NOK_STREAK", "SourceName": "station",
                          "Retain": True, "Severity": 500}], on_vs
