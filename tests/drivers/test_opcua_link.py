"""The OPC UA link (OPC 40100-1 Machine Vision) against asyncua's own Client as the independent
peer: the model, result events, methods, users, certificates, a client that leaves mid-job.

One server for the module (importing the Machine Vision NodeSet takes seconds), Basic256Sha256
SignAndEncrypt, the client's certificate trusted the way an engineer trusts one (copied into
``<pki_dir>/trusted``). The station side is a small StationHandler of the test's own.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import shutil
import socket
import sys
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from opcua_events import Events
from opcua_handler import AT, PASSWORDS, RecordingHandler, link_config
from pydantic import ValidationError
from waiting import until

from drivers.links import link_class, link_settings
from drivers.links.base import (
    AlarmNotice,
    LinkOutcome,
    LinkRequest,
)
from drivers.links.opcua import (
    MV_URI,
    MVPOSE_URI,
    NodeSetError,
    OpcUaLink,
    import_order,
    nodeset_path,
)
from drivers.links.opcua.settings import OpcUaLinkConfig, hash_password
from mvpose_core.reasons import Reason

MODULE_LOOP = pytest.mark.asyncio(loop_scope="module")  # the one server's loop

CLIENT_URI = "urn:mvpose:test:client"


class Served:
    def __init__(self, link: OpcUaLink, handler: RecordingHandler, pki: Path, certs: Path):
        self.link, self.handler, self.pki, self.certs = link, handler, pki, certs

    @property
    def url(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.link.port}/mvpose"

    async def client_cert(self, name: str, trusted: bool) -> tuple[Path, Path]:
        key, cert = self.certs / f"{name}.pem", self.certs / f"{name}.der"
        await setup_self_signed_certificate(key, cert, CLIENT_URI, socket.gethostname(),
                                            [ExtendedKeyUsageOID.CLIENT_AUTH],
                                            {"commonName": name})
        if trusted:
            shutil.copy(cert, self.pki / "trusted" / cert.name)
        return key, cert

    async def client(self, user: str | None = "olga", password: str | None = None,
                     cert: tuple[Path, Path] | None = None) -> Client:
        client = Client(self.url, timeout=10, watchdog_intervall=10)
        client.application_uri = CLIENT_URI
        key, crt = cert or self.default_cert
        await client.set_security(SecurityPolicyBasic256Sha256, certificate=str(crt),
                                  private_key=str(key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        if user is not None:
            client.set_user(user)
            client.set_password(password if password is not None else PASSWORDS[user])
        await client.connect()
        return client

    default_cert: tuple[Path, Path]


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Served]:
    root = tmp_path_factory.mktemp("opcua")
    pki, certs = root / "pki", root / "certs"
    certs.mkdir()
    handler = RecordingHandler()
    # no spacing between management calls here (many calls); its own test sets it
    link = link_class("opcua")(link_config(pki, query_spacing_s=0.0), handler)
    assert isinstance(link, OpcUaLink)
    await link.start()
    assert not link.ready() and link.status()["starting"]  # the NodeSet loads in the background
    await link.wait_ready(120)
    assert link.ready() and link.started.is_set()
    s = Served(link, handler, pki, certs)
    s.default_cert = await s.client_cert("trusted-client", trusted=True)
    try:
        yield s
    finally:
        await link.stop()


async def _vision_system(client: Client) -> tuple[Any, int, int]:
    mv = await client.get_namespace_index(MV_URI)
    own = await client.get_namespace_index(MVPOSE_URI)
    vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
    return vs, mv, own


@MODULE_LOOP
async def test_the_vision_system_is_browsable_with_its_state_machine(served: Served) -> None:
    client = await served.client()
    try:
        vs, mv, own = await _vision_system(client)
        vst = await client.nodes.base_object_type.get_child(f"{mv}:VisionSystemType")
        assert await vs.read_type_definition() == vst.nodeid
        names = {(await c.read_browse_name()).Name for c in await vs.get_children()}
        assert {"VisionStateMachine", "RecipeManagement", "ResultManagement"} <= names, names
        sm = await vs.get_child(f"{mv}:VisionStateMachine")
        state = await (await sm.get_child("0:CurrentState")).read_value()
        auto = await sm.get_child(f"{mv}:AutomaticModeStateMachine")
        mode = await (await auto.get_child("0:CurrentState")).read_value()
        assert (state.Text, mode.Text) == ("Operational", "Ready")  # recipe 1 is selected
        state_id = await (await sm.get_child(["0:CurrentState", "0:Id"])).read_value()
        smt = client.get_node(await sm.read_type_definition())
        assert state_id == (await smt.get_child(f"{mv}:Operational")).nodeid
        number = await vs.get_child([f"{mv}:RecipeManagement", f"{own}:ActiveRecipe",
                                     f"{own}:Number"])
        assert await number.read_value() == 1
        assert import_order() == [nodeset_path("Opc.Ua.MachineVision.NodeSet2.xml")]
    finally:
        await client.disconnect()


async def _subscribe(client: Client, standard: bool = False) -> Events:
    """Result events: of our subtype (every field), or of the standard's ResultReadyEventType
    (what a generic OPC 40100 client asks for)."""
    await client.load_data_type_definitions()
    vs, mv, own = await _vision_system(client)
    path = [f"{mv}:ResultReadyEventType"]
    if not standard:
        path.append(f"{own}:MvposeResultReadyEventType")
    etype = await client.nodes.base_event_type.get_child(path)
    events = Events(timeout_s=10.0)
    sub = await client.create_subscription(50, events)
    await sub.subscribe_events(vs, etype)
    return events


@MODULE_LOOP
async def test_a_method_call_triggers_and_each_result_is_one_event_with_its_record_id(
        served: Served) -> None:
    client = await served.client()
    try:
        events = await _subscribe(client)
        generic = await _subscribe(client, standard=True)
        vs, mv, own = await _vision_system(client)
        rid, code, offset, s_mm, s_deg = await vs.call_method(
            f"{own}:Measure", ua.Variant("VIN-1", ua.VariantType.String),
            ua.Variant(0, ua.VariantType.UInt16), ua.Variant(7, ua.VariantType.UInt32))
        req, out = served.handler.records[-1]
        assert (req.link, req.trigger_id, req.part_id) == ("opcua", 7, "VIN-1")
        assert (rid, code, offset, s_mm) == (out.result_id, 0, list(out.offset), 0.05)
        ev = await events.next()
        assert ev.ResultId.Id == str(out.result_id) and ev.ResultNumber == out.result_id
        assert (ev.PartId.Id, ev.ResultCode, ev.ResultState) == ("VIN-1", 0, 1)
        assert ev.Offset == list(out.offset) and ev.SigmaTranslationMm == 0.05
        assert [c.Value for c in ev.ResultContent] == [*out.offset, 0.05, 0.01]  # offset, 1σ
        std = await generic.next()
        assert (std.ResultId.Id, std.PartId.Id, std.ResultState) == (str(out.result_id),
                                                                     "VIN-1", 1)
        # every Mandatory field of ResultReadyEventType, as GetResultById has the record
        assert (std.IsPartial, std.CreationTime, std.JobId.Id) == (False, AT, "7")
        assert (std.InternalRecipeId.Id, std.InternalRecipeId.Version) == ("recipe-1", "1")
        assert (std.InternalConfigurationId.Id, std.InternalConfigurationId.Version) == (
            "cal-b", "2")
        assert (std.ProcessingTimes.StartTime, std.ProcessingTimes.ProcessingDuration) == (
            AT, 12.0)

        # StartSingleJob (the standard's trigger) answers at once; the result follows as event
        auto = await vs.get_child([f"{mv}:VisionStateMachine", f"{mv}:AutomaticModeStateMachine"])
        job, err = await auto.call_method(
            f"{mv}:StartSingleJob", ua.MeasIdDataType(Id="8"), ua.PartIdDataType(Id="VIN-2"),
            ua.RecipeIdExternalDataType(Id=""), ua.ProductIdDataType(Id=""), ua.Variant())
        assert (job.Id, err) == ("8", 0)
        ev = await events.next()
        assert (ev.ResultId.Id, ev.PartId.Id, ev.JobId.Id) == (
            str(served.handler.records[-1][1].result_id), "VIN-2", "8")

        # a result another link caused (Modbus, REST) is published too, and readable
        other = served.handler.record(
            LinkRequest("modbus", 9, 0, None, "VIN-3", 0),
            LinkOutcome(int(Reason.MARKS_MISSING), 0), "NOK")
        ev = await events.next()
        assert (ev.ResultId.Id, ev.ResultCode, ev.ResultState, ev.Reason) == (
            str(other.result_id), int(Reason.MARKS_MISSING), -int(Reason.MARKS_MISSING),
            "MARKS_MISSING")
        last = await vs.get_child([f"{mv}:ResultManagement", f"{own}:LastResult"])
        assert await (await last.get_child(f"{own}:ResultNumber")).read_value() == \
            other.result_id
        assert events.queue.empty()  # one event per record, no more
    finally:
        await client.disconnect()


@MODULE_LOOP
async def test_halt_refuses_jobs_until_reset(served: Served) -> None:
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        vs, mv, own = await _vision_system(client)
        sm = await vs.get_child(f"{mv}:VisionStateMachine")
        auto = await sm.get_child(f"{mv}:AutomaticModeStateMachine")
        state = await sm.get_child("0:CurrentState")

        async def job() -> int:
            _, err = await auto.call_method(
                f"{mv}:StartSingleJob", ua.MeasIdDataType(Id=""), ua.PartIdDataType(Id="VIN-H"),
                ua.RecipeIdExternalDataType(Id=""), ua.ProductIdDataType(Id=""), ua.Variant())
            return int(err)

        before, resets = len(served.handler.records), served.handler.resets
        assert await sm.call_method(f"{mv}:Halt", ua.Variant(0, ua.VariantType.Int32),
                                    ua.Variant("", ua.VariantType.String)) == 0
        assert (await state.read_value()).Text == "Halted"
        assert await job() == int(Reason.BUSY)
        assert await sm.call_method(f"{mv}:SelectModeAutomatic") == int(Reason.BUSY)
        assert len(served.handler.records) == before
        assert await sm.call_method(f"{mv}:Reset", ua.Variant(0, ua.VariantType.Int32),
                                    ua.Variant("", ua.VariantType.String)) == 0
        assert ((await state.read_value()).Text, served.handler.resets) == ("Operational",
                                                                           resets + 1)
        assert await sm.call_method(f"{mv}:SelectModeAutomatic") == 0
    finally:
        await client.disconnect()


@MODULE_LOOP
async def test_prepare_recipe_selects_by_number_and_names_unknown_ones(served: Served) -> None:
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        vs, mv, own = await _vision_system(client)
        rm = await vs.get_child(f"{mv}:RecipeManagement")
        internal, done, err = await rm.call_method(
            f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id="2"),
            ua.RecipeIdInternalDataType(Id=""))
        assert (done, err, served.handler.recipe) == (True, 0, 2)
        assert (internal.Id, internal.Version, internal.Hash) == ("recipe-2", "4", b"\x02" * 32)
        number = await rm.get_child([f"{own}:ActiveRecipe", f"{own}:Number"])
        assert await number.read_value() == 2
        _, done, err = await rm.call_method(
            f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id="9"),
            ua.RecipeIdInternalDataType(Id=""))
        assert (done, err, served.handler.recipe) == (False, int(Reason.UNKNOWN_RECIPE), 2)
        await rm.call_method(f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id="1"),
                             ua.RecipeIdInternalDataType(Id=""))
    finally:
        await client.disconnect()


@MODULE_LOOP
async def test_wrong_password_unknown_user_and_the_read_role_are_refused(served: Served) -> None:
    for user, password in (("olga", "wrong"), ("mallory", "operator-pw"), (None, None)):
        with pytest.raises(ua.UaError) as err:
            await served.client(user, password)
        assert "BadUserAccessDenied" in repr(err.value) or "BadIdentityToken" in repr(err.value)
    reader = await served.client("rita")
    try:
        vs, mv, own = await _vision_system(reader)
        assert await vs.read_browse_name()  # reading is fine
        before = len(served.handler.records)
        with pytest.raises(ua.UaError, match="BadUserAccessDenied"):
            await vs.call_method(f"{own}:Measure", "VIN-R", ua.Variant(0, ua.VariantType.UInt16),
                                 ua.Variant(1, ua.VariantType.UInt32))
        assert len(served.handler.records) == before
    finally:
        await reader.disconnect()


@MODULE_LOOP
async def test_an_untrusted_client_certificate_is_refused_and_kept_for_review(
        served: Served) -> None:
    stranger = await served.client_cert("stranger", trusted=False)
    with pytest.raises((ua.UaError, ConnectionError, asyncio.TimeoutError)):
        await served.client(cert=stranger)
    kept = list((served.pki / "rejected").glob("*.der"))
    assert kept and any(k.read_bytes() == stranger[1].read_bytes() for k in kept)
    assert any("refused" in e for e in served.link.status()["last_errors"])
    # trusting it (copying it to trusted/) is enough, no restart
    shutil.copy(stranger[1], served.pki / "trusted" / "stranger.der")
    client = await served.client(cert=stranger)
    await client.disconnect()


@MODULE_LOOP
async def test_a_client_gone_mid_measurement_still_gets_its_record_and_the_server_stays_up(
        served: Served) -> None:
    h = served.handler
    h.gate, h.started = asyncio.Event(), asyncio.Event()
    client = await served.client()
    vs, mv, own = await _vision_system(client)
    call = asyncio.ensure_future(vs.call_method(
        f"{own}:Measure", "VIN-GONE", ua.Variant(0, ua.VariantType.UInt16),
        ua.Variant(55, ua.VariantType.UInt32)))
    await asyncio.wait_for(h.started.wait(), 10)
    watcher = await served.client("rita")
    try:
        wvs, _, _ = await _vision_system(watcher)
        state = await (await wvs.get_child([f"{mv}:VisionStateMachine",
                                            f"{mv}:AutomaticModeStateMachine", "0:CurrentState"])
                       ).read_value()
    finally:
        await watcher.disconnect()
    assert state.Text == "SingleExecution"
    client.uaclient.protocol.transport.abort()  # the cable is pulled
    with pytest.raises((ConnectionError, ua.UaError, asyncio.CancelledError, TimeoutError)):
        await call
    before = len(h.records)
    h.gate.set()
    h.gate = None
    for _ in range(200):
        if len(h.records) > before:
            break
        await asyncio.sleep(0.01)  # polling for the record the handler writes
    req, out = h.records[-1]
    assert (req.trigger_id, req.part_id, out.result_code) == (55, "VIN-GONE", 0)
    again = await served.client()
    try:
        vs, mv, own = await _vision_system(again)
        last = await vs.get_child([f"{mv}:ResultManagement", f"{own}:LastResult",
                                   f"{own}:ResultNumber"])
        for _ in range(200):
            if await last.read_value() == out.result_id:
                break
            await asyncio.sleep(0.01)
        assert await last.read_value() == out.result_id
    finally:
        await again.disconnect()
    assert served.link.ready()


@MODULE_LOOP
async def test_no_security_is_offered_only_when_the_station_file_says_so(served: Served) -> None:
    client = Client(served.url, timeout=10, watchdog_intervall=10)
    endpoints = await client.connect_and_get_server_endpoints()
    modes = {(e.SecurityPolicyUri.rsplit("#", 1)[-1], e.SecurityMode.name) for e in endpoints}
    assert modes == {("Basic256Sha256", "Sign"), ("Basic256Sha256", "SignAndEncrypt")}
    assert all(t.TokenType != ua.UserTokenType.Anonymous
               for e in endpoints for t in e.UserIdentityTokens)
    explicit = OpcUaLinkConfig(security=("None",))
    assert explicit.security == ("None",)
    assert "opcua" not in link_settings({})  # no OPC UA unless the station file has the block


def test_station_file_users_need_a_password_hash_never_a_password(tmp_path: Path) -> None:
    with pytest.raises(ValidationError, match="never a plain password"):
        OpcUaLinkConfig.model_validate(
            {"users": {"olga": {"role": "operator", "password_hash": "operator-pw"}}})
    with pytest.raises(ValidationError, match="role"):
        OpcUaLinkConfig.model_validate(
            {"users": {"olga": {"role": "admin", "password_hash": hash_password("x", 10_000)}}})
    with pytest.raises(ValidationError, match="extra"):
        OpcUaLinkConfig.model_validate({"secutiry": ["None"]})


def test_a_nodeset_that_is_not_the_pinned_one_is_refused(tmp_path: Path) -> None:
    path = nodeset_path("Opc.Ua.MachineVision.NodeSet2.xml")
    with pytest.raises(NodeSetError, match="sha256"):
        nodeset_path(path.name, folder=_tampered(path, tmp_path))
    with pytest.raises(NodeSetError, match="missing"):
        nodeset_path(path.name, folder=tmp_path / "empty")


def _tampered(path: Path, tmp_path: Path) -> Path:
    copy = tmp_path / path.name
    copy.write_bytes(path.read_bytes().replace(b"VisionSystemType", b"VisionSystemTypo", 1))
    return tmp_path


@pytest.mark.asyncio  # a server of its own, on the test's own loop
async def test_security_none_and_anonymous_readers_only_when_listed(tmp_path: Path) -> None:
    handler = RecordingHandler()
    pki = tmp_path / "pki"
    link = OpcUaLink(link_config(pki, security=["None"], allow_anonymous=True), handler)
    await link.start()
    try:
        await link.wait_ready(120)
        assert not pki.exists()  # no certificate without a secured endpoint
        url = f"opc.tcp://127.0.0.1:{link.port}/mvpose"
        probe = Client(url, timeout=10, watchdog_intervall=10)
        endpoints = await probe.connect_and_get_server_endpoints()
        assert {e.SecurityMode for e in endpoints} == {ua.MessageSecurityMode.None_}
        client = Client(url, timeout=10, watchdog_intervall=10)  # no user, no certificate
        await client.connect()
        try:
            vs, mv, own = await _vision_system(client)
            assert (await vs.read_browse_name()).Name == "VisionSystem"
            with pytest.raises(ua.UaError, match="BadUserAccessDenied"):  # anonymous = read
                await vs.call_method(f"{own}:Measure", "VIN-A",
                                     ua.Variant(0, ua.VariantType.UInt16),
                                     ua.Variant(1, ua.VariantType.UInt32))
            assert handler.records == []
        finally:
            await client.disconnect()
    finally:
        await link.stop()
    assert not link.ready()


# ---------------------------------------------------------------------------- management
async def _parts(client: Client) -> dict[str, Any]:
    vs, mv, own = await _vision_system(client)
    sm = await vs.get_child(f"{mv}:VisionStateMachine")
    auto = await sm.get_child(f"{mv}:AutomaticModeStateMachine")
    return {"vs": vs, "mv": mv, "own": own, "sm": sm, "auto": auto,
            "auto_state": await auto.get_child("0:CurrentState"),
            "rm": await vs.get_child(f"{mv}:RecipeManagement"),
            "res": await vs.get_child(f"{mv}:ResultManagement"),
            "cm": await vs.get_child(f"{mv}:ConfigurationManagement")}


def _timeout() -> ua.Variant:
    return ua.Variant(0, ua.VariantType.Int32)


def _u32(n: int) -> ua.Variant:
    return ua.Variant(n, ua.VariantType.UInt32)


async def _results(p: dict[str, Any], state: int = 0, meas: str = "", part: str = "",
                   ext_recipe: str = "", recipe: str = "", config: str = "", job: str = "",
                   max_results: int = 0, start: int = 0) -> list[Any]:
    return list(await p["res"].call_method(
        f"{p['mv']}:GetResultListFiltered", ua.Variant(state, ua.VariantType.Int32),
        ua.MeasIdDataType(Id=meas), ua.PartIdDataType(Id=part),
        ua.RecipeIdExternalDataType(Id=ext_recipe), ua.RecipeIdInternalDataType(Id=recipe),
        ua.ConfigurationIdDataType(Id=""), ua.ConfigurationIdDataType(Id=config),
        ua.ProductIdDataType(Id=""), ua.JobIdDataType(Id=job), _u32(max_results), _u32(start),
        _timeout()))


def _store(h: RecordingHandler, trigger_id: int, part: str, code: int = 0) -> LinkOutcome:
    req = LinkRequest("modbus", trigger_id, 0, None, part, 0)
    offset = (1.0, 2.0, 3.0, 0.1, 0.2, 0.3) if code == 0 else None
    return h.record(req, LinkOutcome(code, 0, offset, 0.05, 0.01), "OK" if code == 0 else "NOK")


@MODULE_LOOP
async def test_a_result_is_read_by_its_id_whole_or_in_components(served: Served) -> None:
    h = served.handler
    ok = _store(h, 501, "VIN-ID")
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        p = await _parts(client)
        handle, result, err = await p["res"].call_method(
            f"{p['mv']}:GetResultById", ua.ResultIdDataType(Id=str(ok.result_id)), _timeout())
        assert (handle, err) == (0, 0)
        assert isinstance(result, ua.ResultDataType)
        assert (result.ResultId.Id, result.MeasId.Id, result.JobId.Id, result.PartId.Id) == (
            str(ok.result_id), "501", "501", "VIN-ID")
        assert (result.ResultState, result.IsPartial) == (1, False)
        assert (result.InternalRecipeId.Id, result.InternalRecipeId.Version) == ("recipe-1", "1")
        assert (result.InternalConfigurationId.Id, result.InternalConfigurationId.Version) == (
            "cal-b", "2")
        assert result.InternalConfigurationId.Hash == bytes.fromhex("bb" * 32)
        assert [c.Value for c in result.ResultContent] == [*ok.offset, 0.05, 0.01]
        assert result.CreationTime == AT and result.ProcessingTimes.ProcessingDuration == 12.0

        out = await p["res"].call_method(
            f"{p['mv']}:GetResultComponentsById", ua.ResultIdDataType(Id=str(ok.result_id)),
            _timeout())
        assert len(out) == 17 and out[-1] == 0
        assert (out[4], out[5].Id, out[6].Id, out[8].Id, out[12].Id) == (
            1, "501", "VIN-ID", "recipe-1", "501")
        assert [c.Value for c in out[15]] == [*ok.offset, 0.05, 0.01]

        nok = _store(h, 502, "VIN-ID", int(Reason.MARKS_MISSING))
        _, result, err = await p["res"].call_method(
            f"{p['mv']}:GetResultById", ua.ResultIdDataType(Id=str(nok.result_id)), _timeout())
        assert (err, result.ResultState, result.ResultContent) == (
            0, -int(Reason.MARKS_MISSING), None)

        for unknown in ("999999", "abc", ""):
            before = len(served.link.last_errors)
            handle, result, err = await p["res"].call_method(
                f"{p['mv']}:GetResultById", ua.ResultIdDataType(Id=unknown), _timeout())
            assert (handle, err, result.ResultId.Id) == (0, int(Reason.BAD_ARGUMENT), "")
            assert f"no result with ResultId {unknown!r}" in served.link.last_errors[-1]
            assert len(served.link.last_errors) == before + 1
            out = await p["res"].call_method(
                f"{p['mv']}:GetResultComponentsById", ua.ResultIdDataType(Id=unknown),
                _timeout())
            assert out[-1] == int(Reason.BAD_ARGUMENT)
    finally:
        await client.disconnect()


@MODULE_LOOP
async def test_the_result_list_filters_and_pages(served: Served) -> None:
    h = served.handler
    made = [_store(h, 600 + i, "VIN-LIST", 0 if i % 3 else int(Reason.TOO_FEW_MARKS))
            for i in range(7)]  # 600, 603, 606 NOK
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        p = await _parts(client)
        complete, count, handle, items, err = await _results(p, part="VIN-LIST")
        assert (complete, count, handle, err) == (True, 7, 0, 0)
        assert [r.ResultId.Id for r in items] == [str(o.result_id) for o in made]  # oldest first

        pages = []
        for start in (0, 3, 6):
            complete, count, _, items, err = await _results(p, part="VIN-LIST", max_results=3,
                                                            start=start)
            pages.append((complete, count, [int(r.MeasId.Id) for r in items]))
        assert pages == [(False, 3, [600, 601, 602]), (False, 3, [603, 604, 605]),
                         (True, 1, [606])]
        _, count, _, items, _ = await _results(p, part="VIN-LIST", start=50)
        assert (count, items) == (0, [])

        nok = [r.MeasId.Id for r in (await _results(p, part="VIN-LIST", state=4))[3]]
        assert nok == ["600", "603", "606"]
        assert len((await _results(p, part="VIN-LIST", state=1))[3]) == 4
        by_reason = await _results(p, part="VIN-LIST", state=-int(Reason.TOO_FEW_MARKS))
        assert by_reason[1] == 3
        assert (await _results(p, part="VIN-LIST", state=2))[1] == 0  # nothing is Processing
        assert [r.PartId.Id for r in (await _results(p, meas="604"))[3]] == ["VIN-LIST"]
        assert (await _results(p, job="605", part="VIN-LIST"))[1] == 1
        assert (await _results(p, meas="604", job="605"))[1] == 0
        assert (await _results(p, part="VIN-LIST", recipe="recipe-1"))[1] == 7
        assert (await _results(p, part="VIN-LIST", ext_recipe="1"))[1] == 7
        assert (await _results(p, part="VIN-LIST", ext_recipe="2"))[1] == 0
        *_, err = await _results(p, ext_recipe="9")
        assert err == int(Reason.UNKNOWN_RECIPE)
        *_, err = await _results(p, config="cal-b")
        assert err == int(Reason.BAD_ARGUMENT)
        assert "not filtered by configuration" in served.link.last_errors[-1]
    finally:
        await client.disconnect()


@MODULE_LOOP
async def test_the_read_role_calls_no_method_and_only_an_engineer_activates(
        served: Served) -> None:
    reader = await served.client("rita")
    operator = await served.client("olga")
    try:
        await reader.load_data_type_definitions()
        p = await _parts(reader)
        before = served.handler.queries
        with pytest.raises(ua.UaError, match="BadUserAccessDenied"):
            await p["res"].call_method(f"{p['mv']}:GetResultById",
                                       ua.ResultIdDataType(Id="1"), _timeout())
        with pytest.raises(ua.UaError, match="BadUserAccessDenied"):
            await p["rm"].call_method(
                f"{p['mv']}:UnprepareRecipe", ua.RecipeIdExternalDataType(Id="1"),
                ua.RecipeIdInternalDataType(Id=""))
        assert served.handler.queries == before and served.handler.recipe == 1
        await operator.load_data_type_definitions()
        o = await _parts(operator)
        with pytest.raises(ua.UaError, match="BadUserAccessDenied"):
            await o["cm"].call_method(f"{o['mv']}:ActivateConfiguration",
                                      ua.ConfigurationIdDataType(Id="", Version="1"))
        assert [c.version for c in served.handler.calibs if c.active] == [2]
        # the operator's other calls still work
        _, _, err = await o["res"].call_method(
            f"{o['mv']}:GetResultById", ua.ResultIdDataType(Id="1"), _timeout())
        assert err == int(Reason.BAD_ARGUMENT)
    finally:
        await reader.disconnect()
        await operator.disconnect()


@MODULE_LOOP
async def test_configurations_are_the_calibration_versions(served: Served) -> None:
    h = served.handler
    client = await served.client("erik")
    try:
        await client.load_data_type_definitions()
        p = await _parts(client)
        mv = p["mv"]
        active = await (await p["cm"].get_child(f"{mv}:ActiveConfiguration")).read_value()
        assert isinstance(active, ua.ConfigurationDataType)
        assert (active.InternalId.Id, active.InternalId.Version) == ("cal-b", "2")
        complete, count, handle, items, err = await p["cm"].call_method(
            f"{mv}:GetConfigurationList", _u32(0), _u32(0), _timeout())
        assert (complete, count, handle, err) == (True, 2, 0, 0)
        assert [(c.InternalId.Id, c.InternalId.Version) for c in items] == [
            ("cal-a", "1"), ("cal-b", "2")]
        complete, count, _, items, _ = await p["cm"].call_method(
            f"{mv}:GetConfigurationList", _u32(1), _u32(0), _timeout())
        assert (complete, count) == (False, 1)
        _, config, err = await p["cm"].call_method(
            f"{mv}:GetConfigurationById", ua.ConfigurationIdDataType(Id="", Version="1"),
            _timeout())
        assert (err, config.InternalId.Id, config.LastModified) == (0, "cal-a", AT)
        for wrong in (ua.ConfigurationIdDataType(Id="", Version="7"),
                      ua.ConfigurationIdDataType(Id="cal-b", Version="1"),
                      ua.ConfigurationIdDataType(Id="cal-a")):
            _, config, err = await p["cm"].call_method(
                f"{mv}:GetConfigurationById", wrong, _timeout())
            assert (err, config.InternalId.Id) == (int(Reason.BAD_ARGUMENT), "")
            assert await p["cm"].call_method(f"{mv}:ActivateConfiguration", wrong) == \
                int(Reason.BAD_ARGUMENT)
        # the station refuses version 2 (in this handler): its reason is the Error
        assert await p["cm"].call_method(
            f"{mv}:ActivateConfiguration", ua.ConfigurationIdDataType(Id="", Version="2")) == \
            int(Reason.BAD_ARGUMENT)
        assert "does not fit" in served.link.last_errors[-1]
        assert await p["cm"].call_method(
            f"{mv}:ActivateConfiguration",
            ua.ConfigurationIdDataType(Id="cal-a", Version="1")) == 0
        assert [c.version for c in h.calibs if c.active] == [1]
        active = await (await p["cm"].get_child(f"{mv}:ActiveConfiguration")).read_value()
        assert (active.InternalId.Id, active.InternalId.Version) == ("cal-a", "1")
    finally:
        await client.disconnect()


@MODULE_LOOP
async def test_recipes_are_listed_and_unprepared(served: Served) -> None:
    h = served.handler
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        p = await _parts(client)
        mv, rm = p["mv"], p["rm"]

        async def listed(external: str = "", prepared: int = 2, max_results: int = 0,
                         start: int = 0) -> tuple[bool, int, list[tuple[str, str, str]], int]:
            complete, count, handle, items, err = await rm.call_method(
                f"{mv}:GetRecipeListFiltered", ua.RecipeIdExternalDataType(Id=external),
                ua.ProductIdDataType(Id=""), ua.Variant(prepared, ua.VariantType.Int32),
                _u32(max_results), _u32(start), _timeout())
            assert handle == 0
            return complete, count, [(r.Id, r.Version, r.Description.Text) for r in items], err

        assert await listed() == (True, 2, [("recipe-1", "3", "recipe number 1"),
                                            ("recipe-2", "4", "recipe number 2")], 0)
        assert await listed(prepared=1) == (True, 1, [("recipe-1", "3", "recipe number 1")], 0)
        assert (await listed(prepared=0))[2][0][0] == "recipe-2"
        assert (await listed(external="2"))[2][0][0] == "recipe-2"
        assert (await listed(external="9"))[:2] == (True, 0)
        assert (await listed(max_results=1))[:2] == (False, 1)
        assert (await listed(max_results=1, start=1))[:3] == (
            True, 1, [("recipe-2", "4", "recipe number 2")])

        async def unprepare(external: str) -> tuple[str, int]:
            out, err = await rm.call_method(
                f"{mv}:UnprepareRecipe", ua.RecipeIdExternalDataType(Id=external),
                ua.RecipeIdInternalDataType(Id=""))
            return out.Id, err

        assert await unprepare("9") == ("", int(Reason.UNKNOWN_RECIPE))
        assert await unprepare("2") == ("recipe-2", int(Reason.BAD_ARGUMENT))  # not prepared
        assert h.recipe == 1
        assert await unprepare("1") == ("recipe-1", 0)
        assert h.recipe == 0
        assert (await p["auto_state"].read_value()).Text == "Initialized"
        assert (await listed(prepared=1))[1] == 0
        # continuous mode needs a recipe: refused up front, nothing recorded
        before = len(h.records)
        job, err = await p["auto"].call_method(
            f"{mv}:StartContinuous", ua.MeasIdDataType(Id=""), ua.PartIdDataType(Id="VIN-U"),
            ua.RecipeIdExternalDataType(Id=""), ua.ProductIdDataType(Id=""), ua.Variant())
        assert (job.Id, err, len(h.records)) == ("", int(Reason.UNKNOWN_RECIPE), before)
        _, done, err = await rm.call_method(
            f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id="1"),
            ua.RecipeIdInternalDataType(Id=""))
        assert (done, err, h.recipe) == (True, 0, 1)
        assert (await p["auto_state"].read_value()).Text == "Ready"
    finally:
        await client.disconnect()


def _permits(n: int) -> asyncio.Queue[None]:
    """Measurements the test handler may finish, one token each."""
    q: asyncio.Queue[None] = asyncio.Queue()
    for _ in range(n):
        q.put_nowait(None)
    return q


async def _start_continuous(p: dict[str, Any], meas: str, part: str) -> tuple[str, int]:
    job, err = await p["auto"].call_method(
        f"{p['mv']}:StartContinuous", ua.MeasIdDataType(Id=meas), ua.PartIdDataType(Id=part),
        ua.RecipeIdExternalDataType(Id=""), ua.ProductIdDataType(Id=""), ua.Variant())
    return job.Id, int(err)


async def _wait_records(h: RecordingHandler, part: str, n: int) -> list[LinkOutcome]:
    await until(lambda: len([1 for req, _ in h.records if req.part_id == part]) >= n)
    return [out for req, out in h.records if req.part_id == part]


@MODULE_LOOP
async def test_continuous_mode_measures_back_to_back_until_stop(served: Served) -> None:
    h = served.handler
    h.permits = _permits(0)
    entered = h.entered
    client = await served.client()
    try:
        events = await _subscribe(client)
        p = await _parts(client)
        mv = p["mv"]
        assert await _start_continuous(p, "700", "VIN-C") == ("700", 0)
        assert (await p["auto_state"].read_value()).Text == "ContinuousExecution"
        assert await _start_continuous(p, "", "VIN-X") == ("", int(Reason.BUSY))
        job, err = await p["auto"].call_method(
            f"{mv}:StartSingleJob", ua.MeasIdDataType(Id=""), ua.PartIdDataType(Id="VIN-X"),
            ua.RecipeIdExternalDataType(Id=""), ua.ProductIdDataType(Id=""), ua.Variant())
        assert err == int(Reason.BUSY)
        for _ in range(5):
            h.permits.put_nowait(None)
        outs = await _wait_records(h, "VIN-C", 5)
        got = [await events.next() for _ in range(5)]
        assert [e.ResultId.Id for e in got] == [str(o.result_id) for o in outs]
        triggers = [req.trigger_id for req, _ in h.records if req.part_id == "VIN-C"]
        assert triggers[0] == 700 and len(set(triggers)) == 5
        assert {req.link for req, _ in h.records if req.part_id == "VIN-C"} == {"opcua"}
        # the sixth job waits inside the station; Stop lets it finish, then Ready
        await until(lambda: h.entered == entered + 6)
        stop = asyncio.ensure_future(p["auto"].call_method(
            f"{mv}:Stop", ua.Variant(0, ua.VariantType.Int32),
            ua.Variant("", ua.VariantType.String)))
        await until(lambda: served.link.machine.stop_requested)
        assert not stop.done()  # Stop waits for the running job
        h.permits.put_nowait(None)
        assert await asyncio.wait_for(stop, 10) == 0
        assert len(await _wait_records(h, "VIN-C", 6)) == 6
        assert (await p["auto_state"].read_value()).Text == "Ready"
        assert served.link.machine.continuous is None and not served.link.machine.jobs
        assert (await events.next()).PartId.Id == "VIN-C"  # the sixth's event
        assert len([1 for req, _ in h.records if req.part_id == "VIN-C"]) == 6  # no seventh
        assert await p["auto"].call_method(
            f"{mv}:Stop", ua.Variant(0, ua.VariantType.Int32),
            ua.Variant("", ua.VariantType.String)) == int(Reason.BAD_ARGUMENT)  # nothing runs
    finally:
        h.permits = None
        await client.disconnect()


@MODULE_LOOP
async def test_abort_is_ready_at_once_and_the_running_job_keeps_its_record(
        served: Served) -> None:
    h = served.handler
    h.permits = _permits(1)
    entered = h.entered
    resets = h.resets
    client = await served.client()
    try:
        p = await _parts(client)
        mv = p["mv"]
        assert (await _start_continuous(p, "", "VIN-A"))[1] == 0
        await until(lambda: h.entered == entered + 2)  # the second job is inside the station
        assert await p["auto"].call_method(
            f"{mv}:Abort", ua.Variant(0, ua.VariantType.Int32),
            ua.Variant("", ua.VariantType.String)) == 0
        assert (await p["auto_state"].read_value()).Text == "Ready"
        assert h.resets == resets + 1  # a half-done multi-view sequence is dropped
        assert len([1 for req, _ in h.records if req.part_id == "VIN-A"]) == 1
        h.permits.put_nowait(None)
        outs = await _wait_records(h, "VIN-A", 2)  # the aborted job's record still comes
        assert outs[1].result_code == 0
        assert (await p["auto_state"].read_value()).Text == "Ready"
        assert served.link.machine.continuous is None
    finally:
        h.permits = None
        await client.disconnect()


@MODULE_LOOP
async def test_halt_ends_continuous_mode(served: Served) -> None:
    h = served.handler
    h.permits = _permits(2)
    entered = h.entered
    client = await served.client()
    try:
        p = await _parts(client)
        mv, sm = p["mv"], p["sm"]
        assert (await _start_continuous(p, "", "VIN-HC"))[1] == 0
        await until(lambda: h.entered == entered + 3)  # the third waits inside the station
        assert await sm.call_method(f"{mv}:Halt", ua.Variant(0, ua.VariantType.Int32),
                                    ua.Variant("", ua.VariantType.String)) == 0
        assert (await (await sm.get_child("0:CurrentState")).read_value()).Text == "Halted"
        assert served.link.machine.continuous is None
        h.permits.put_nowait(None)  # the job waiting inside the station ends with its record
        done = await _wait_records(h, "VIN-HC", 3)
        assert len(done) == 3
        assert await _start_continuous(p, "", "VIN-HC") == ("", int(Reason.BUSY))
        assert await sm.call_method(f"{mv}:Reset", ua.Variant(0, ua.VariantType.Int32),
                                    ua.Variant("", ua.VariantType.String)) == 0
        assert (await p["auto_state"].read_value()).Text == "Ready"
    finally:
        h.permits = None
        await client.disconnect()


@MODULE_LOOP
async def test_a_client_of_its_own_decodes_the_machine_vision_structures(
        served: Served) -> None:
    """A client in another process (no types from our server in its asyncua.ua) loads the
    definitions from the server and decodes ResultDataType, ConfigurationDataType and
    RecipeIdInternalDataType: the link completes the NodeSet's id types' definitions
    (FreeOpcUa/opcua-asyncio#1693 otherwise)."""
    ok = _store(served.handler, 801, "VIN-OWN")
    key, cert = served.default_cert
    script = Path(__file__).with_name("opcua_client.py")

    async def run() -> dict[str, Any]:
        proc = await asyncio.create_subprocess_exec(
            sys.executable, str(script), served.url, str(key), str(cert), "olga",
            PASSWORDS["olga"], str(ok.result_id),
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE)
        out, err = await asyncio.wait_for(proc.communicate(), 60)
        assert proc.returncode == 0, err.decode()[-2000:]
        decoded: dict[str, Any] = json.loads(out)
        return decoded

    decoded = await run()
    using = next(c for c in served.handler.calibs if c.in_use)
    assert decoded == {
        "known": {"ResultDataType": True, "ConfigurationDataType": True,
                  "RecipeIdInternalDataType": True},
        "error": 0, "type": "ResultDataType", "result_id": str(ok.result_id),
        "part_id": "VIN-OWN", "recipe": ["recipe-1", "1"],
        "configuration": ["cal-b", "2"], "state": 1,
        "content": [*(ok.offset or ()), 0.05, 0.01],
        "active_configuration": [using.calibration_id, str(using.version)],
        "configuration_1": [0, "cal-a", "1"],
        "recipes": ["recipe-1", "recipe-2"],
    }


@MODULE_LOOP
async def test_continuous_mode_ends_when_the_station_gives_no_answer(served: Served) -> None:
    h = served.handler
    h.fail = True
    client = await served.client()
    try:
        p = await _parts(client)
        assert (await _start_continuous(p, "", "VIN-F"))[1] == 0
        await until(lambda: served.link.machine.continuous is None)
        outs = await _wait_records(h, "VIN-F", 1)
        assert [o.result_code for o in outs] == [int(Reason.HANDLER_FAILED)]  # not a storm
        assert "continuous mode ended" in served.link.last_errors[-1]
        assert (await p["auto_state"].read_value()).Text == "Ready"
    finally:
        h.fail = False
        await client.disconnect()


@MODULE_LOOP
async def test_management_calls_are_spaced_whichever_client_calls(served: Served) -> None:
    """Each call costs the station process Python time beside the trigger thread: calls of
    every client together start at most every query_spacing_s."""
    ok = _store(served.handler, 901, "VIN-SPACE")
    clients = [await served.client(), await served.client()]
    served.link.management.spacing_s = 0.3
    try:
        loop = asyncio.get_running_loop()
        t0 = loop.time()

        async def get(client: Client) -> float:
            p = await _parts(client)
            _, result, err = await p["res"].call_method(
                f"{p['mv']}:GetResultById", ua.ResultIdDataType(Id=str(ok.result_id)),
                _timeout())
            assert (err, result.PartId.Id) == (0, "VIN-SPACE")
            return loop.time() - t0

        done = sorted(await asyncio.gather(*(get(c) for c in clients * 2)))
        assert done[-1] >= 3 * 0.3, done  # four calls: three spacings at least
    finally:
        served.link.management.spacing_s = 0.0
        for c in clients:
            await c.disconnect()


@MODULE_LOOP
async def test_station_alarms_are_machine_vision_condition_events(served: Served) -> None:
    """OPC 40100-1 §11.4: an error (high priority) is a VisionErrorConditionType event, a
    warning a VisionWarningConditionType one, each with ErrorCode and ErrorString and Part 9's
    condition state; a generic client subscribing to VisionConditionType gets both."""
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        vs, mv, _ = await _vision_system(client)
        etype = await client.nodes.base_event_type.get_child(
            ["0:ConditionType", "0:AcknowledgeableConditionType", f"{mv}:VisionConditionType"])
        events = Events(timeout_s=10.0)
        sub = await client.create_subscription(50, events)
        await sub.subscribe_events(vs, etype)
        raised = AlarmNotice("raised", 41, 7, "link:modbus", "LINK_NO_PLC", "high",
                             "link modbus: no PLC heartbeat", True, False, None, AT)
        served.link.alarm_changed(raised)
        ev = await events.next()
        error = await client.nodes.base_event_type.get_child(
            ["0:ConditionType", "0:AcknowledgeableConditionType", f"{mv}:VisionConditionType",
             f"{mv}:VisionErrorConditionType"])
        assert ev.EventType == error.nodeid
        assert (ev.ConditionName, ev.SourceName, ev.ErrorCode, ev.ErrorString) == (
            "LINK_NO_PLC", "link:modbus", 7, "link modbus: no PLC heartbeat")
        assert (ev.Severity, ev.Retain, ev.Message.Text, ev.Time) == (
            800, True, "link modbus: no PLC heartbeat", AT)
        acked = dataclasses.replace(raised, event="acknowledged", event_id=42,
                                    acknowledged=True, acked_by="alice", priority="medium")
        served.link.alarm_changed(acked)
        ev = await events.next()
        assert ev.EventType != error.nodeid  # a warning: VisionWarningConditionType
        assert (ev.Severity, ev.Retain, ev.ClientUserId) == (500, True, "alice")
        cleared = dataclasses.replace(acked, event="cleared", event_id=43, active=False)
        served.link.alarm_changed(cleared)
        ev = await events.next()
        assert (ev.Retain, ev.Comment.Text) == (False, "cleared")
        assert served.link.status()["alarms_published"] >= 3
        await sub.delete()
    finally:
        await client.disconnect()
