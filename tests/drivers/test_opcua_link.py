"""The OPC UA link (OPC 40100-1 Machine Vision) against asyncua's own Client as the independent
peer: the model, result events, methods, users, certificates, a client that leaves mid-job.

One server for the module (importing the Machine Vision NodeSet takes seconds), Basic256Sha256
SignAndEncrypt, the client's certificate trusted the way an engineer trusts one (copied into
``<pki_dir>/trusted``). The station side is a small StationHandler of the test's own.
"""

from __future__ import annotations

import asyncio
import shutil
import socket
import threading
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from pydantic import ValidationError

from drivers.links import link_class
from drivers.links.base import LinkOutcome, LinkRequest
from drivers.links.opcua import (
    MV_URI,
    MVPOSE_URI,
    NodeSetError,
    OpcUaLink,
    import_order,
    nodeset_path,
)
from mvpose_core.linkconfig import LinksConfig, OpcUaLinkConfig, hash_password
from mvpose_core.reasons import Reason
from mvpose_core.transforms import RobotConvention

MODULE_LOOP = pytest.mark.asyncio(loop_scope="module")  # the one server's loop

PASSWORDS = {"olga": "operator-pw", "rita": "reader-pw"}
CLIENT_URI = "urn:mvpose:test:client"


class RecordingHandler:
    """A station that records every answer with the next seq and tells its listeners (from a
    thread of its own, as the station's recorder thread does)."""

    def __init__(self) -> None:
        self.seq = 100
        self.records: list[tuple[LinkRequest, LinkOutcome]] = []
        self.listeners: list[Callable[[dict[str, Any]], None]] = []
        self.recipe = 1
        self.gate: asyncio.Event | None = None
        self.started = asyncio.Event()
        self.resets = 0

    def measure(self, request: LinkRequest) -> asyncio.Future[LinkOutcome]:
        return asyncio.ensure_future(self._measure(request))

    async def _measure(self, request: LinkRequest) -> LinkOutcome:
        self.started.set()
        if self.gate is not None:
            await self.gate.wait()
        t = request.trigger_id
        out = LinkOutcome(0, 0, offset=(t * 0.5, -1.0, 2.0, 0.1, 0.2, -0.3),
                          sigma_trans_mm=0.05, sigma_rot_deg=0.01, processing_ms=12.0)
        return self.record(request, out, "OK")

    def record(self, request: LinkRequest, out: LinkOutcome, result: str) -> LinkOutcome:
        self.seq += 1
        out = LinkOutcome(out.result_code, self.seq, out.offset, out.sigma_trans_mm,
                          out.sigma_rot_deg, out.processing_ms)
        self.records.append((request, out))
        event = {
            "result_id": self.seq, "trigger_id": request.trigger_id, "part_id": request.part_id,
            "recipe": f"recipe-{self.recipe}", "result": result, "reason_code": out.result_code,
            "reason": Reason(out.result_code).name, "message": "", "processing_ms": 12.0,
            "at": "2026-11-23T23:00:00+00:00", "convention": "fanuc",
            "offset": list(out.offset) if out.offset else None,
            "sigma_mm": out.sigma_trans_mm, "sigma_deg": out.sigma_rot_deg,
        }
        for listen in self.listeners:
            th = threading.Thread(target=listen, args=(event,))
            th.start()
            th.join()
        return out

    async def record_failure(self, request: LinkRequest, code: int, message: str,
                             processing_ms: float) -> int:
        return self.record(request, LinkOutcome(code, 0), "NOK").result_id

    async def select_recipe(self, number: int) -> int:
        if number not in (1, 2):
            return int(Reason.UNKNOWN_RECIPE)
        self.recipe = number
        return 0

    async def teach_reference(self, by: str) -> int:
        return 0

    async def reset(self) -> None:
        self.resets += 1

    def convention(self) -> RobotConvention:
        return RobotConvention.FANUC

    def selected_recipe(self) -> int:
        return self.recipe

    def add_listener(self, listen: Callable[[dict[str, Any]], None]) -> None:
        self.listeners.append(listen)


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
        client = Client(self.url, timeout=10)
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


def _config(pki: Path, **extra: Any) -> OpcUaLinkConfig:
    users = {"olga": {"role": "operator", "password_hash": hash_password("operator-pw", 10_000)},
             "rita": {"role": "read", "password_hash": hash_password("reader-pw", 10_000)}}
    return OpcUaLinkConfig.model_validate({"port": 0, "pki_dir": str(pki), "users": users,
                                           "measure_timeout_s": 5.0, **extra})


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Served]:
    root = tmp_path_factory.mktemp("opcua")
    pki, certs = root / "pki", root / "certs"
    certs.mkdir()
    handler = RecordingHandler()
    link = link_class("opcua")(_config(pki), handler)
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


class _Events:
    def __init__(self) -> None:
        self.queue: asyncio.Queue[Any] = asyncio.Queue()

    def event_notification(self, event: Any) -> None:
        self.queue.put_nowait(event)

    async def next(self) -> Any:
        return await asyncio.wait_for(self.queue.get(), 10)


async def _subscribe(client: Client, standard: bool = False) -> _Events:
    """Result events: of our subtype (every field), or of the standard's ResultReadyEventType
    (what a generic OPC 40100 client asks for)."""
    await client.load_data_type_definitions()
    vs, mv, own = await _vision_system(client)
    path = [f"{mv}:ResultReadyEventType"]
    if not standard:
        path.append(f"{own}:MvposeResultReadyEventType")
    etype = await client.nodes.base_event_type.get_child(path)
    events = _Events()
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
        std = await generic.next()
        assert (std.ResultId.Id, std.PartId.Id, std.ResultState) == (str(out.result_id),
                                                                     "VIN-1", 1)

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
            str(other.result_id), int(Reason.MARKS_MISSING), 2, "MARKS_MISSING")
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
    client = Client(served.url, timeout=10)
    endpoints = await client.connect_and_get_server_endpoints()
    modes = {(e.SecurityPolicyUri.rsplit("#", 1)[-1], e.SecurityMode.name) for e in endpoints}
    assert modes == {("Basic256Sha256", "Sign"), ("Basic256Sha256", "SignAndEncrypt")}
    assert all(t.TokenType != ua.UserTokenType.Anonymous
               for e in endpoints for t in e.UserIdentityTokens)
    explicit = OpcUaLinkConfig(security=("None",))
    assert explicit.security == ("None",)
    assert LinksConfig().opcua is None  # no OPC UA server unless the station file has the block


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


@MODULE_LOOP
async def test_security_none_and_anonymous_readers_only_when_listed(tmp_path: Path) -> None:
    handler = RecordingHandler()
    pki = tmp_path / "pki"
    link = OpcUaLink(_config(pki, security=["None"], allow_anonymous=True), handler)
    await link.start()
    try:
        await link.wait_ready(120)
        assert not pki.exists()  # no certificate without a secured endpoint
        url = f"opc.tcp://127.0.0.1:{link.port}/mvpose"
        probe = Client(url, timeout=10)
        endpoints = await probe.connect_and_get_server_endpoints()
        assert {e.SecurityMode for e in endpoints} == {ua.MessageSecurityMode.None_}
        client = Client(url, timeout=10)  # no user, no certificate
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
