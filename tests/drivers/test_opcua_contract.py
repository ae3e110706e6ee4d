"""The OPC UA link keeps its contract as a second client stack sees it (issue 23, item 4).

node-opcua's client (tests/node_opcua.py, tests/peers/node-opcua) beside asyncua's: sessions only
on the security the station file lists, every Mandatory field of ResultReadyEventType filled,
standard ``OfType`` filters, events through the Server object, Call arguments checked with the
standard status codes, SystemState truthful. One server for the module (the NodeSet import takes
seconds), Basic256Sha256 Sign and SignAndEncrypt; the station side is the tests' own handler.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import socket
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import node_opcua
import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from opcua_handler import PASSWORDS, RecordingHandler, link_config
from waiting import until

from drivers.links.opcua import MV_URI, OpcUaLink

MODULE_LOOP = pytest.mark.asyncio(loop_scope="module")
PEER_URI = "urn:mvpose:test:node-opcua"


class Served:
    def __init__(self, link: OpcUaLink, handler: RecordingHandler, pki: Path, root: Path,
                 key: Path, cert: Path) -> None:
        self.link, self.handler, self.pki, self.root = link, handler, pki, root
        self.key, self.cert = key, cert

    @property
    def url(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.link.port}/mvpose"

    async def peer(self, steps: list[dict[str, Any]], mode: str = "SignAndEncrypt",
                   policy: str = "Basic256Sha256", user: str | None = "olga",
                   insist: bool = False) -> dict[str, Any]:
        """node-opcua's client: ``steps`` over a channel of ``mode`` / ``policy`` (``insist``:
        even one the server does not offer)."""
        return await node_opcua.run({
            "url": self.url, "mode": mode, "policy": policy, "cert": str(self.cert),
            "key": str(self.key), "pki": str(self.root / "node-pki"),
            "applicationUri": PEER_URI, "user": user,
            "password": PASSWORDS.get(user or "", ""), "insist": insist,
            "serverCert": str(self.pki / "server_cert.der"), "steps": steps})

    async def client(self, user: str = "olga") -> Client:
        client = Client(self.url, timeout=10, watchdog_intervall=10)
        client.application_uri = PEER_URI
        await client.set_security(SecurityPolicyBasic256Sha256, certificate=str(self.cert),
                                  private_key=str(self.key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        client.set_user(user)
        client.set_password(PASSWORDS[user])
        await client.connect()
        return client


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Served]:
    root = tmp_path_factory.mktemp("opcua-contract")
    pki = root / "pki"
    handler = RecordingHandler()
    # a job held inside the station (SystemState) must not meet the link's backstop on a busy host
    link = OpcUaLink(link_config(pki, query_spacing_s=0.0, measure_timeout_s=300.0), handler)
    await link.start()
    await link.wait_ready(120)
    key, cert = root / "peer_key.pem", root / "peer_cert.der"
    await setup_self_signed_certificate(key, cert, PEER_URI, socket.gethostname(),
                                        [ExtendedKeyUsageOID.CLIENT_AUTH],
                                        {"commonName": "node-opcua peer"})
    shutil.copy(cert, pki / "trusted" / cert.name)
    try:
        yield Served(link, handler, pki, root, key, cert)
    finally:
        await link.stop()


def _measure(trigger: int, part: str = "VIN-N") -> dict[str, Any]:
    return {"do": "call", "object": ["mv:VisionSystem"], "method": "mvpose:Measure",
            "args": [{"type": "String", "value": part}, {"type": "UInt16", "value": 0},
                     {"type": "UInt32", "value": trigger}]}


# ---------------------------------------------------------------------------- security
@MODULE_LOOP
async def test_a_session_over_an_unlisted_none_channel_is_refused(
        served: Served, caplog: pytest.LogCaptureFixture) -> None:
    """node-opcua made to insist on None (the station lists Basic256Sha256 only): discovery
    works, CreateSession is refused, so the password is never sent; nothing is measured."""
    before = len(served.handler.records)
    with caplog.at_level(logging.INFO, logger="asyncua.server.uaprocessor"):
        got = await served.peer([{"do": "endpoints"}, {"do": "session"}, _measure(1)],
                                mode="None", policy="None", insist=True)
    assert got["connected"], got  # discovery (GetEndpoints) over None stays possible
    assert sorted(map(tuple, got["results"][0])) == [("Basic256Sha256", "Sign"),
                                                     ("Basic256Sha256", "SignAndEncrypt")]
    assert got["error"].startswith("session:") and "BadSecurityPolicyRejected" in got["error"]
    said = [r.getMessage() for r in caplog.records]
    assert any("Create session request" in m for m in said), said
    assert not any("Activate session request" in m for m in said), said  # no user token sent
    assert len(served.handler.records) == before  # nothing measured, nothing stored



@MODULE_LOOP
async def test_a_security_mode_the_station_file_does_not_list_gets_no_session(
        served: Served) -> None:
    """A station that lists Sign only: a client that insists on SignAndEncrypt (it knows the
    server's certificate, so it opens the channel without looking at the endpoints) gets no
    session; Sign is the one endpoint and works."""
    pki = served.root / "pki-sign-only"
    link = OpcUaLink(link_config(pki, security=["Basic256Sha256_Sign"]), served.handler)
    await link.start()
    try:
        await link.wait_ready(120)
        (pki / "trusted").mkdir(parents=True, exist_ok=True)
        shutil.copy(served.cert, pki / "trusted" / served.cert.name)
        other = Served(link, served.handler, pki, served.root, served.key, served.cert)
        before = len(served.handler.records)
        got = await other.peer([{"do": "session"}, _measure(2)], mode="SignAndEncrypt",
                               insist=True)
        # the channel opens for discovery only: the session is refused at once, by name
        assert got["error"].startswith("session:"), got
        assert "BadSecurityPolicyRejected" in got["error"], got
        assert len(served.handler.records) == before
        listed = await other.peer([{"do": "endpoints"}, _measure(3, "VIN-SIGN")], mode="Sign")
        assert listed["results"][0] == [["Basic256Sha256", "Sign"]], listed
        assert listed["results"][1]["status"] == "Good"
    finally:
        await link.stop()

# ---------------------------------------------------------------------------- result events
MANDATORY = ["mv:ResultId", "mv:IsPartial", "mv:ResultState", "mv:JobId", "mv:CreationTime",
             "mv:InternalRecipeId", "mv:InternalConfigurationId"]
OPTIONAL = ["mv:MeasId", "mv:PartId", "mv:ProcessingTimes", "mv:ResultContent"]


def _subscribe(label: str, node: Any, fields: list[str]) -> dict[str, Any]:
    """A standard client's subscription: OfType ResultReadyEventType (node-opcua's
    constructEventFilter, one OfType operator), on ``node``."""
    return {"do": "subscribe", "label": label, "node": node, "ofType": ["mv:ResultReadyEventType"],
            "fields": ["EventType", "SourceNode", *fields]}


@MODULE_LOOP
async def test_an_of_type_filter_gets_every_mandatory_field_on_the_vision_system_and_server(
        served: Served) -> None:
    got = await served.peer([
        _subscribe("vs", ["mv:VisionSystem"], MANDATORY + OPTIONAL),
        _subscribe("server", "Server", MANDATORY),
        {**_subscribe("base", ["mv:VisionSystem"], ["mv:ResultId"]), "ofType": "BaseEventType"},
        _measure(31, "VIN-EV"),
        {"do": "wait_events", "label": "vs", "count": 1},
        {"do": "wait_events", "label": "server", "count": 1},
        {"do": "wait_events", "label": "base", "count": 1},
    ])
    assert "error" not in got, got
    call, on_vs, on_server, on_base = got["results"][3:]
    assert call["status"] == "Good" and call["outputs"][1] == 0
    rid = call["outputs"][0]
    stored = served.handler.stored[rid]
    assert (len(on_vs), len(on_server), len(on_base)) == (1, 1, 1), got  # OfType missed them
    ev = on_vs[0]
    assert ev["mv:ResultId"]["id"] == str(rid)
    assert ev["mv:IsPartial"] is False
    assert ev["mv:ResultState"] == 1
    assert ev["mv:JobId"]["id"] == ev["mv:MeasId"]["id"] == "31"
    assert ev["mv:PartId"]["id"] == "VIN-EV"
    assert ev["mv:CreationTime"] == stored.triggered_at.isoformat().replace("+00:00", ".000Z")
    assert (ev["mv:InternalRecipeId"]["id"], ev["mv:InternalRecipeId"]["version"]) == (
        stored.recipe, str(stored.recipe_version))
    assert (ev["mv:InternalConfigurationId"]["id"],
            ev["mv:InternalConfigurationId"]["version"]) == ("cal-b", "2")
    times = ev["mv:ProcessingTimes"]
    assert times["startTime"] == ev["mv:CreationTime"]
    assert times["endTime"] > times["startTime"] and times["processingDuration"] == 12.0
    assert ev["mv:ResultContent"] == [*(stored.offset or ()), 0.05, 0.01]
    assert on_server[0]["mv:ResultId"] == on_base[0]["mv:ResultId"] == ev["mv:ResultId"]
    assert all(on_server[0][f] is not None for f in MANDATORY), on_server[0]


# ---------------------------------------------------------------------------- call arguments
def _call(obj: list[str], method: str, *args: tuple[str, Any]) -> dict[str, Any]:
    return {"do": "call", "object": obj, "method": method,
            "args": [{"type": t, "value": value} for t, value in args]}


@MODULE_LOOP
async def test_call_arguments_are_checked_with_the_standard_status_codes(served: Served) -> None:
    before = len(served.handler.records)
    vs, auto = ["mv:VisionSystem"], ["mv:VisionSystem", "mv:VisionStateMachine",
                                     "mv:AutomaticModeStateMachine"]
    got = await served.peer([
        _call(vs, "mvpose:Measure", ("String", "VIN-T"), ("String", "1"), ("UInt32", 5)),
        _call(vs, "mvpose:Measure", ("String", "VIN-T"), ("UInt32", 1), ("UInt32", 5)),
        _call(vs, "mvpose:Measure", ("String", "VIN-T"), ("UInt16", 0)),
        _call(vs, "mvpose:Measure", ("String", "VIN-T"), ("UInt16", 0), ("UInt32", 5),
              ("UInt32", 6)),
        _call(auto, "mv:StartSingleJob", ("String", "8"), ("String", "VIN-T"), ("String", ""),
              ("String", ""), ("Null", None)),
        _call(["mv:VisionSystem", "mv:ResultManagement"], "mv:GetResultById"),
    ])
    assert "error" not in got, got
    wrong, wider, missing, extra, job, nothing = got["results"]
    assert (wrong["status"], wrong["inputArgumentResults"]) == (
        "BadInvalidArgument", ["Good", "BadTypeMismatch", "Good"])
    assert (wider["status"], wider["inputArgumentResults"]) == (  # no implicit conversion
        "BadInvalidArgument", ["Good", "BadTypeMismatch", "Good"])
    assert missing["status"] == "BadArgumentsMissing"
    assert extra["status"] == "BadTooManyArguments"
    assert job["status"] == "BadInvalidArgument"
    assert job["inputArgumentResults"][:3] == ["BadTypeMismatch"] * 3
    assert nothing["status"] == "BadArgumentsMissing"  # not BadUnexpectedError
    assert len(served.handler.records) == before  # nothing measured, nothing stored
    # the right types still measure
    ok = await served.peer([_measure(9, "VIN-T")])
    assert ok["results"][0]["status"] == "Good" and len(served.handler.records) == before + 1


# ---------------------------------------------------------------------------- SystemState
@MODULE_LOOP
async def test_system_state_is_production_while_a_job_runs_and_stand_by_between(
        served: Served) -> None:
    system_state = {"do": "read", "path": ["mv:VisionSystem", "mv:SystemState"]}
    idle = await served.peer([system_state])
    assert "error" not in idle, idle
    assert idle["results"][0]["value"]["state"] == 2  # SBY_2, never NST_6 (the model's default)
    h = served.handler
    h.gate, h.started = asyncio.Event(), asyncio.Event()
    try:
        job = asyncio.ensure_future(served.peer([_measure(41, "VIN-S")]))
        await asyncio.wait_for(h.started.wait(), 60)
        busy = await served.peer([system_state])
        assert busy["results"][0]["value"]["state"] == 1  # PRD_1: the vision system measures
    finally:
        h.gate.set()
        h.gate = None
    assert (await job)["results"][0]["status"] == "Good"
    client = await served.client()
    try:
        await client.load_data_type_definitions()
        mv = await client.get_namespace_index(MV_URI)
        vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
        state = await vs.get_child(f"{mv}:SystemState")
        await until(lambda: _system_state(served.link) == 2, "SBY_2 after the job")
        assert int((await state.read_value()).State) == 2
        sm = await vs.get_child(f"{mv}:VisionStateMachine")
        await sm.call_method(f"{mv}:Halt", ua.Variant(0, ua.VariantType.Int32),
                             ua.Variant("", ua.VariantType.String))
        assert int((await state.read_value()).State) == 4  # SDT_4: halted on request
        await sm.call_method(f"{mv}:Reset", ua.Variant(0, ua.VariantType.Int32),
                             ua.Variant("", ua.VariantType.String))
        assert int((await state.read_value()).State) == 2
    finally:
        await client.disconnect()


def _system_state(link: OpcUaLink) -> int:
    """SystemState's State as the server holds it now (its address space, no session)."""
    assert link.server is not None
    value = link.server.iserver.aspace.read_attribute_value(
        link.model.nodes["system_state"].nodeid, ua.AttributeIds.Value).Value
    return int(value.Value.State) if value is not None else 0
