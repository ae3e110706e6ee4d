"""The OPC UA backend of the link seam: a Machine Vision server (OPC 40100-1) with asyncua.

The information model is the OPC Foundation's own NodeSet2 file, installed from the npm package
``node-opcua-nodesets`` (pinned by ``opcua_nodesets/package-lock.json``) and checked against
``opcua_nodesets/SHA256SUMS`` before it is imported: nothing of the model is typed in here. One
``VisionSystem`` object (``VisionSystemType``) stands for the station:

- ``VisionStateMachine``: Operational with its automatic mode (Initialized: no recipe selected,
  Ready, SingleExecution while a job of this link runs), Halted after ``Halt`` until ``Reset``;
- ``RecipeManagement.PrepareRecipe``: selects a recipe by number (``ExternalId.Id``); the active
  recipe's number, name and version are variables next to it;
- ``AutomaticModeStateMachine.StartSingleJob``: one trigger (the same ``StationHandler.measure``
  as Modbus), answered at once with its JobId; the result follows as a ``ResultReadyEvent``;
  ``VisionSystem.Measure`` (mvpose's own method) triggers and waits for the outcome;
- ``ResultManagement``: a ``ResultReadyEvent`` (our subtype ``MvposeResultReadyEventType``) for
  every recorded answer whichever link or client caused it, ``ResultId`` = the record's seq; the
  last result also as variables (``ResultManagement/LastResult``).

Security: Basic256Sha256 Sign / SignAndEncrypt by default with a server certificate made at the
first start in ``pki_dir``; client certificates must be in ``<pki_dir>/trusted`` (refused ones
land in ``<pki_dir>/rejected``); users log in with a name and password checked against the
station file's pbkdf2 hashes and get the read, operator (may call methods) or engineer role.
The server runs on the station's event loop, like the Modbus link.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import os
import socket
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Node, Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.permission_rules import USER_TYPES, SimpleRoleRuleset, User, UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.user_managers import UserManager
from cryptography import x509
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from mvpose_core.linkconfig import OpcUaLinkConfig, check_password
from mvpose_core.reasons import Reason, reason_name

from .base import Link, LinkOutcome, LinkRequest, StationHandler

log = logging.getLogger(__name__)

NODESET_DIR = Path(__file__).resolve().parent / "opcua_nodesets"
NODESET_FILES = NODESET_DIR / "node_modules" / "node-opcua-nodesets" / "nodesets"
MACHINE_VISION = "Opc.Ua.MachineVision.NodeSet2.xml"
MODEL_FILES = {  # ModelUri -> the NodeSet2 file that defines it
    "http://opcfoundation.org/UA/MachineVision": MACHINE_VISION,
    "http://opcfoundation.org/UA/DI/": "Opc.Ua.Di.NodeSet2.xml",
}
MV_URI = "http://opcfoundation.org/UA/MachineVision"
MVPOSE_URI = "urn:mvpose:opcua"  # mvpose's own nodes: our event subtype, Measure, LastResult
UA_NS = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"

POLICIES = {
    "Basic256Sha256_Sign": ua.SecurityPolicyType.Basic256Sha256_Sign,
    "Basic256Sha256_SignAndEncrypt": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    "None": ua.SecurityPolicyType.NoSecurity,
}
_UA: Any = ua  # the NodeSet's structures are made at import time; asyncua's stubs are strict
RESULT_STATE_OK, RESULT_STATE_NOK = 1, 2  # ResultState (vendor-defined in OPC 40100-1)


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


def default_pki_dir() -> Path:
    """``<data_dir>/opcua`` when the station file names no pki_dir (MVPOSE_DATA_DIR, else var)."""
    return Path(os.environ.get("MVPOSE_DATA_DIR", "var")) / "opcua"


# ---------------------------------------------------------------------------- users and roles
class _Users(UserManager):
    """asyncua's user manager: user name + password against the station file's hashes."""

    def __init__(self, config: OpcUaLinkConfig) -> None:
        self.config = config
        self._good: set[tuple[str, str]] = set()  # (name, sha256 of a checked password)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if username is None:
            return User(role=UserRole.Anonymous) if self.config.allow_anonymous else None
        user = self.config.users.get(username)
        if user is None or password is None:
            log.warning("OPC UA: login refused for unknown user %r", username)
            return None
        key = (username, hashlib.sha256(password.encode()).hexdigest())
        if key not in self._good:
            if not check_password(password, user.password_hash):
                log.warning("OPC UA: wrong password for user %r", username)
                return None
            self._good.add(key)  # pbkdf2 runs on the station loop: once per user and password
        return User(role=UserRole.User, name=username)


class _Roles(SimpleRoleRuleset):
    """read: browse, read, subscribe; operator: + call methods; engineer: + write."""

    CALL = _UA.NodeId(ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
    WRITE = _UA.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)

    def __init__(self, config: OpcUaLinkConfig) -> None:
        super().__init__()
        self.config = config
        every = {_UA.NodeId(t) for t in USER_TYPES}
        read = every - {self.CALL, self.WRITE}
        self.allowed = {"read": read, "operator": read | {self.CALL}, "engineer": every}

    def role(self, user: User | None) -> str | None:
        if user is None:
            return None
        if user.name is not None and user.name in self.config.users:
            return self.config.users[user.name].role
        if user.role == UserRole.Anonymous and self.config.allow_anonymous:
            return "read"
        return None

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        role = self.role(user)
        return role is not None and action_type_id in self.allowed[role]


# ---------------------------------------------------------------------------- the link
class OpcUaLink(Link):
    """OPC UA server with the station's VisionSystem object."""

    name = "opcua"
    config: OpcUaLinkConfig

    def __init__(self, config: OpcUaLinkConfig, handler: StationHandler) -> None:
        super().__init__(config, handler)
        self.server: Server | None = None
        self.port_bound = 0
        self.load_s: dict[str, float] = {}
        self.state = "Preoperational"
        self.auto_state = "Initialized"
        self.jobs = 0  # OPC UA jobs running
        self.results = 0  # ResultReadyEvents sent
        self.triggers = 0
        self.last_errors: list[str] = []
        self._listening = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: set[asyncio.Future[Any]] = set()
        self._trigger_id = 0
        self._nodes: dict[str, Node] = {}
        self._state_ids: dict[str, ua.NodeId] = {}
        self._evgen: Any = None
        self._lock = asyncio.Lock()  # variable writes and events in order
        self._t0 = 0.0
        self._order: list[Path] = []
        self._pki: Path | None = None
        self._boot_task: asyncio.Future[Any] | None = None
        self.started = threading.Event()  # the endpoint listens (for threads and other loops)
        self.failed: str | None = None
        self._made: Server | None = None

    # ------------------------------------------------------------------ life cycle
    async def start(self) -> None:
        """Check at once what can fail (the NodeSets against their pinned hashes, the server
        certificate), then build and open the server in the background: importing the Machine
        Vision NodeSet takes seconds (docs/integration.md), more than a station gives its links
        to start. Until the endpoint listens, ready() is False and status() says starting."""
        self._loop = asyncio.get_running_loop()
        self._t0 = time.monotonic()
        self._order = import_order()
        if any(p != "None" for p in self.config.security):
            await self._make_certificate()
        self._boot_task = self._spawn(self._boot())

    async def wait_ready(self, timeout_s: float) -> None:
        """Until the endpoint listens (on the station's loop); raises what the start raised."""
        if self._boot_task is not None:
            await asyncio.wait_for(asyncio.shield(self._boot_task), timeout_s)

    async def _boot(self) -> None:
        cfg = self.config
        try:
            t = time.monotonic()
            server = self._made = Server(user_manager=_Users(cfg))
            await server.init()
            self.load_s["init"] = time.monotonic() - t
            server.set_server_name("mvpose station")
            await server.set_application_uri(cfg.application_uri)
            server.set_endpoint(f"opc.tcp://{cfg.host}:{cfg.port}/mvpose")
            server.set_security_policy([POLICIES[p] for p in cfg.security],
                                       permission_ruleset=_Roles(cfg))
            tokens: list[type] = [ua.UserNameIdentityToken]
            if cfg.allow_anonymous:
                tokens.append(ua.AnonymousIdentityToken)
            server.set_identity_tokens(tokens)
            if self._pki is not None:
                await self._secure(server, self._pki)
            t = time.monotonic()
            for path in self._order:
                await server.import_xml(str(path), strict_mode=path.name == MACHINE_VISION)
            self.load_s["nodesets"] = time.monotonic() - t
            t = time.monotonic()
            await self._build(server)
            self.load_s["model"] = time.monotonic() - t
            await server.start()
        except Exception as err:
            self.failed = f"the OPC UA server did not start: {type(err).__name__}: {err}"
            log.error("%s", self.failed, exc_info=True)
            raise
        self.server = server
        self.port_bound = server.bserver.port if server.bserver is not None else cfg.port
        self.state = "Operational"
        await self._show_recipe()
        self._listening = True
        self.handler.add_listener(self._on_result)
        self.load_s["total"] = time.monotonic() - self._t0
        self.started.set()
        log.info("OPC UA link on opc.tcp://%s:%d/mvpose (%s); started in %s s", cfg.host,
                 self.port_bound, ", ".join(cfg.security),
                 {k: round(v, 2) for k, v in self.load_s.items()})

    async def stop(self) -> None:
        self._listening = False  # the station has no remove_listener: the callback goes quiet
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        made, self._made, self.server = self._made, None, None
        if made is not None and made.bserver is not None:  # it listens (or did)
            await made.stop()

    @property
    def port(self) -> int:
        if self.server is None:
            raise RuntimeError("the OPC UA link is not started")
        return self.port_bound

    def ready(self) -> bool:
        return self.server is not None

    def status(self) -> dict[str, Any]:
        if self.server is None:
            starting = self._boot_task is not None and not self._boot_task.done()
            return {"running": False, "starting": starting, "error": self.failed}
        return {
            "running": True, "port": self.port_bound, "security": list(self.config.security),
            "state": self.state, "automatic_mode": self.auto_state, "triggers": self.triggers,
            "results_published": self.results, "start_s": {k: round(v, 2)
                                                           for k, v in self.load_s.items()},
            "last_errors": self.last_errors[-5:],
        }

    def recipe_changed(self) -> None:
        if self.server is not None:
            self._spawn(self._show_recipe())

    # ------------------------------------------------------------------ security
    async def _make_certificate(self) -> None:
        """The server's key and self-signed certificate in pki_dir, made at the first start."""
        pki = Path(self.config.pki_dir) if self.config.pki_dir else default_pki_dir()
        for sub in ("", "trusted", "rejected"):
            (pki / sub).mkdir(parents=True, exist_ok=True)
        key, cert = pki / "server_key.pem", pki / "server_cert.der"
        await setup_self_signed_certificate(
            key, cert, self.config.application_uri, socket.gethostname(),
            [ExtendedKeyUsageOID.SERVER_AUTH],
            {"commonName": "mvpose station", "organizationName": "mvpose"})
        key.chmod(0o600)
        self._pki = pki

    async def _secure(self, server: Server, pki: Path) -> None:
        key, cert = pki / "server_key.pem", pki / "server_cert.der"
        await server.load_certificate(str(cert))
        await server.load_private_key(str(key))
        if self.config.trust_all_client_certificates:
            options = CertificateValidatorOptions.BASIC_VALIDATION
            store = None
        else:
            options = (CertificateValidatorOptions.TRUSTED_VALIDATION
                       | CertificateValidatorOptions.PEER_CLIENT)
            store = TrustStore([pki / "trusted"], [])
        checker = CertificateValidator(options, store)
        rejected = pki / "rejected"

        async def validate(certificate: x509.Certificate, app: ua.ApplicationDescription) -> None:
            if store is not None:
                await store.load_trust()  # a certificate copied into trusted/ counts at once
            try:
                await checker.validate(certificate, app)
            except ServiceError as err:
                der = certificate.public_bytes(Encoding.DER)
                kept = rejected / f"{hashlib.sha1(der).hexdigest()}.der"  # noqa: S324 - a name
                kept.write_bytes(der)
                text = (f"client certificate of {app.ApplicationUri!r} refused "
                        f"({_UA.StatusCode(err.code).name}); kept as {kept}: move it to "
                        f"{pki / 'trusted'} to trust it")
                log.warning("OPC UA: %s", text)
                self._error(text)
                raise

        server.set_certificate_validator(validate)

    # ------------------------------------------------------------------ the address space
    async def _build(self, server: Server) -> None:
        mv = await server.get_namespace_index(MV_URI)
        idx = await server.register_namespace(MVPOSE_URI)
        types = server.nodes.base_object_type
        vst = await types.get_child([f"{mv}:VisionSystemType"])
        vs = await server.nodes.objects.add_object(_UA.NodeId("VisionSystem", idx),
                                                   f"{mv}:VisionSystem", objecttype=vst.nodeid)
        await vs.set_event_notifier([ua.EventNotifier.SubscribeToEvents])
        sm = await vs.get_child(f"{mv}:VisionStateMachine")
        auto = await sm.get_child(f"{mv}:AutomaticModeStateMachine")
        rm = await vs.get_child(f"{mv}:RecipeManagement")
        res = await vs.get_child(f"{mv}:ResultManagement")
        n = self._nodes
        n["vs"], n["sm"], n["auto"] = vs, sm, auto
        n["sm_state"] = await sm.get_child("0:CurrentState")
        n["auto_state"] = await auto.get_child("0:CurrentState")
        sm_type = server.get_node(_typedef(await sm.read_type_definition()))
        auto_type = server.get_node(_typedef(await auto.read_type_definition()))
        for state in ("Preoperational", "Halted", "Error", "Operational"):
            self._state_ids[state] = (await sm_type.get_child(f"{mv}:{state}")).nodeid
        for state in ("Initialized", "Ready", "SingleExecution", "ContinuousExecution"):
            self._state_ids[state] = (await auto_type.get_child(f"{mv}:{state}")).nodeid

        # methods of the standard: Halt, Reset, SelectModeAutomatic, StartSingleJob, PrepareRecipe
        links: dict[tuple[Node, str], Callable[..., Any]] = {
            (sm, "Halt"): self._halt, (sm, "Reset"): self._reset,
            (sm, "SelectModeAutomatic"): self._select_auto,
            (auto, "StartSingleJob"): self._start_single_job,
            (rm, "PrepareRecipe"): self._prepare_recipe,
        }
        for (parent, method), fn in links.items():
            server.link_method(await parent.get_child(f"{mv}:{method}"), fn)

        # mvpose's own: the active recipe, the last result, Measure, the event subtype
        recipe = await rm.add_object(idx, "ActiveRecipe")
        for name, value, vt in (("Number", 0, ua.VariantType.UInt16),
                                ("Name", "", ua.VariantType.String),
                                ("Version", 0, ua.VariantType.UInt32),
                                ("Convention", "", ua.VariantType.String)):
            n[f"recipe.{name}"] = await recipe.add_variable(idx, name, ua.Variant(value, vt))
        last = await res.add_object(idx, "LastResult")
        for name, value, vt in self._result_fields():
            n[f"last.{name}"] = await last.add_variable(idx, name, ua.Variant(value, vt))
        measure = await vs.add_method(
            idx, "Measure", self._measure,
            [_arg("PartId", ua.ObjectIds.String), _arg("RecipeNumber", ua.ObjectIds.UInt16),
             _arg("TriggerId", ua.ObjectIds.UInt32)],
            [_arg("ResultId", ua.ObjectIds.UInt32), _arg("ResultCode", ua.ObjectIds.Int32),
             _arg("Offset", ua.ObjectIds.Double, rank=1),
             _arg("SigmaTranslationMm", ua.ObjectIds.Double),
             _arg("SigmaRotationDeg", ua.ObjectIds.Double)])
        n["measure"] = measure
        rre = await types.get_child(["0:BaseEventType", f"{mv}:ResultReadyEventType"])
        props = [(name, vt) for name, _, vt in self._result_fields()
                 if name not in ("PartId", "CreationTime")]
        etype = await server.create_custom_event_type(idx, "MvposeResultReadyEventType",
                                                      rre.nodeid, props)
        self._evgen = await server.get_event_generator(etype, vs.nodeid)

    @staticmethod
    def _result_fields() -> list[tuple[str, Any, ua.VariantType]]:
        return [
            ("ResultNumber", 0, ua.VariantType.UInt32), ("TriggerId", 0, ua.VariantType.UInt32),
            ("PartId", "", ua.VariantType.String), ("Recipe", "", ua.VariantType.String),
            ("ResultCode", 0, ua.VariantType.Int32), ("Reason", "", ua.VariantType.String),
            ("ResultMessage", "", ua.VariantType.String),
            ("Offset", [], ua.VariantType.Double), ("Convention", "", ua.VariantType.String),
            ("SigmaTranslationMm", 0.0, ua.VariantType.Double),
            ("SigmaRotationDeg", 0.0, ua.VariantType.Double),
            ("ProcessingMs", 0.0, ua.VariantType.Double),
            ("CreationTime", datetime.now(UTC), ua.VariantType.DateTime),
        ]

    # ------------------------------------------------------------------ states
    async def _show_states(self) -> None:
        if self.state == "Operational":
            self.auto_state = ("SingleExecution" if self.jobs else
                               "Ready" if self.handler.selected_recipe() else "Initialized")
        for key, state in (("sm_state", self.state), ("auto_state", self.auto_state)):
            node = self._nodes[key]
            active = key == "sm_state" or self.state == "Operational"
            text = state if active else ""
            await node.write_value(ua.LocalizedText(text))
            await (await node.get_child("0:Id")).write_value(
                self._state_ids[state] if active else ua.NodeId())

    async def _show_recipe(self) -> None:
        number = self.handler.selected_recipe()
        name, version = _recipe_label(self.handler)
        n = self._nodes
        await n["recipe.Number"].write_value(ua.Variant(number, ua.VariantType.UInt16))
        await n["recipe.Name"].write_value(ua.Variant(name, ua.VariantType.String))
        await n["recipe.Version"].write_value(ua.Variant(version, ua.VariantType.UInt32))
        await n["recipe.Convention"].write_value(
            ua.Variant(self.handler.convention().value if number else "", ua.VariantType.String))
        if self.server is not None:
            await self._show_states()

    # ------------------------------------------------------------------ methods
    async def _halt(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        self.state = "Halted"
        await self._show_states()
        return [_int32(0)]

    async def _reset(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        await self.handler.reset()
        self.state = "Operational"
        await self._show_states()
        return [_int32(0)]

    async def _select_auto(self, parent: ua.NodeId, *args: ua.Variant) -> list[ua.Variant]:
        if self.state == "Halted":
            return [_int32(int(Reason.BUSY))]
        self.state = "Operational"  # automatic is the station's only mode
        await self._show_states()
        return [_int32(0)]

    async def _prepare_recipe(self, parent: ua.NodeId, external: ua.Variant,
                              internal: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        wanted = _struct_id(external.Value) or _struct_id(internal.Value)
        code = int(Reason.BAD_ARGUMENT)
        if wanted.isdigit() and 0 < int(wanted) <= 65535:
            code = await self.handler.select_recipe(int(wanted))
        if code == 0:
            await self._show_recipe()
        out = _recipe_id(ua, "RecipeIdInternalDataType", *_recipe_label(self.handler))
        return [ua.Variant(out), ua.Variant(code == 0, ua.VariantType.Boolean), _int32(code)]

    async def _start_single_job(self, parent: ua.NodeId, meas: ua.Variant, part: ua.Variant,
                                recipe: ua.Variant, *rest: ua.Variant) -> list[ua.Variant]:
        number = _struct_id(recipe.Value)
        if self.state != "Operational":
            return [ua.Variant(_UA.JobIdDataType(Id="")), _int32(int(Reason.BUSY))]
        if number and not number.isdigit():
            return [ua.Variant(_UA.JobIdDataType(Id="")), _int32(int(Reason.BAD_ARGUMENT))]
        trigger_id = self._next_trigger(_struct_id(meas.Value))
        req = self._request(trigger_id, _struct_id(part.Value), int(number or 0))
        self._spawn(self._job(req))
        return [ua.Variant(_UA.JobIdDataType(Id=str(trigger_id))), _int32(0)]

    async def _measure(self, parent: ua.NodeId, part: ua.Variant, recipe: ua.Variant,
                       trigger: ua.Variant) -> list[ua.Variant]:
        if self.state != "Operational":
            out = LinkOutcome(int(Reason.BUSY), 0)
        else:
            req = self._request(self._next_trigger(str(trigger.Value or "")), str(part.Value or ""),
                                int(recipe.Value or 0))
            # shielded: a client that goes away mid-measurement does not cancel the record
            out = await asyncio.shield(self._spawn(self._job(req)))
        offset = list(out.offset) if out.offset is not None else []
        return [ua.Variant(out.result_id, ua.VariantType.UInt32), _int32(out.result_code),
                ua.Variant(offset, ua.VariantType.Double),
                ua.Variant(out.sigma_trans_mm, ua.VariantType.Double),
                ua.Variant(out.sigma_rot_deg, ua.VariantType.Double)]

    def _next_trigger(self, wanted: str) -> int:
        if wanted.isdigit() and 0 < int(wanted) < 2**32:
            return int(wanted)
        self._trigger_id = self._trigger_id % (2**32 - 1) + 1
        return self._trigger_id

    def _request(self, trigger_id: int, part_id: str, recipe: int) -> LinkRequest:
        return LinkRequest(link="opcua", trigger_id=trigger_id, view_index=0, robot_pose=None,
                           part_id=part_id, recipe=recipe)

    async def _job(self, req: LinkRequest) -> LinkOutcome:
        """One trigger through the station, with the link's own recorded backstop."""
        self.triggers += 1
        self.jobs += 1
        await self._show_states()
        t0 = time.monotonic()
        try:
            limit = self.config.measure_timeout_s
            try:
                return await asyncio.wait_for(self.handler.measure(req), limit)
            except TimeoutError:
                code, text = int(Reason.TIMEOUT), f"no answer within {limit} s (OPC UA link)"
            except Exception as err:  # noqa: BLE001 - recorded with its text
                log.exception("OPC UA trigger %d failed", req.trigger_id)
                code, text = int(Reason.HANDLER_FAILED), f"{type(err).__name__}: {err}"
            self._error(f"trigger {req.trigger_id}: {text}")
            ms = (time.monotonic() - t0) * 1e3
            rid = await self.handler.record_failure(req, code, text, ms)
            return LinkOutcome(code, rid, processing_ms=ms)
        finally:
            self.jobs -= 1
            if self.server is not None:
                await self._show_states()

    # ------------------------------------------------------------------ results
    def _on_result(self, result: dict[str, Any]) -> None:
        """The station's listener (trigger or recorder thread): publish on our loop."""
        loop = self._loop
        if self._listening and loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(lambda: self._spawn(self._publish(result)))

    async def _publish(self, r: dict[str, Any]) -> None:
        if self.server is None or self._evgen is None:
            return
        ok = r.get("reason_code", 0) == 0 and r.get("result") == "OK"
        at = _time(r.get("at"))
        offset = [float(v) for v in (r.get("offset") or [])]
        values: dict[str, Any] = {
            "ResultNumber": int(r["result_id"]), "TriggerId": int(r.get("trigger_id") or 0),
            "PartId": str(r.get("part_id") or ""), "Recipe": str(r.get("recipe") or ""),
            "ResultCode": int(r.get("reason_code", 0)),
            "Reason": str(r.get("reason") or reason_name(int(r.get("reason_code", 0)))),
            "ResultMessage": str(r.get("message") or ""), "Offset": offset,
            "Convention": str(r.get("convention") or ""),
            "SigmaTranslationMm": float(r.get("sigma_mm") or 0.0),
            "SigmaRotationDeg": float(r.get("sigma_deg") or 0.0),
            "ProcessingMs": float(r.get("processing_ms") or 0.0), "CreationTime": at,
        }
        async with self._lock:
            for name, _, vt in self._result_fields():
                await self._nodes[f"last.{name}"].write_value(ua.Variant(values[name], vt))
            ev = self._evgen.event
            for name, _, vt in self._result_fields():
                if name not in ("PartId", "CreationTime"):
                    setattr(ev, name, ua.Variant(values[name], vt))
            ev.ResultId = _UA.ResultIdDataType(Id=str(values["ResultNumber"]))
            ev.PartId = _UA.PartIdDataType(Id=values["PartId"])
            ev.MeasId = _UA.MeasIdDataType(Id=str(values["TriggerId"]))
            ev.JobId = _UA.JobIdDataType(Id=str(values["TriggerId"]))
            ev.InternalRecipeId = _recipe_id(ua, "RecipeIdInternalDataType", values["Recipe"],
                                             int(r.get("recipe_version") or 0))
            ev.IsPartial = False
            ev.ResultState = ua.Variant(RESULT_STATE_OK if ok else RESULT_STATE_NOK,
                                        ua.VariantType.Int32)
            ev.CreationTime = at
            ev.ResultContent = ua.Variant(offset, ua.VariantType.Double)
            ev.Severity = 100 if ok else 500
            await self._evgen.trigger(
                time_attr=at, message=f"result {values['ResultNumber']}: {values['Reason']}")
            self.results += 1

    # ------------------------------------------------------------------ helpers
    def _spawn(self, coro: Any) -> asyncio.Future[Any]:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)

        def done(t: asyncio.Future[Any]) -> None:
            self._tasks.discard(t)
            if not t.cancelled() and (err := t.exception()) is not None:
                log.error("OPC UA link task failed: %r", err, exc_info=err)
                self._error(f"{type(err).__name__}: {err}")

        task.add_done_callback(done)
        return task

    def _error(self, text: str) -> None:
        self.last_errors = [*self.last_errors[-19:], text]


def _arg(name: str, datatype: int, rank: int = -1) -> ua.Argument:
    arg = ua.Argument()
    arg.Name = name
    arg.DataType = _UA.NodeId(datatype)
    arg.ValueRank = rank
    arg.Description = ua.LocalizedText(name)
    return arg


def _typedef(nodeid: ua.NodeId | None) -> ua.NodeId:
    if nodeid is None:
        raise RuntimeError("an instance of the Machine Vision model has no type definition")
    return nodeid


def _int32(value: int) -> ua.Variant:
    return ua.Variant(int(value), ua.VariantType.Int32)


def _struct_id(value: Any) -> str:
    """The Id field of an OPC 40100 id structure (MeasId, PartId, RecipeId ...), or ''."""
    got = getattr(value, "Id", None)
    if got is None and isinstance(value, str):
        got = value
    return str(got or "").strip()


def _recipe_id(mod: Any, cls: str, name: str, version: int) -> Any:
    return getattr(mod, cls)(Id=name, Version=str(version) if version else None)


def _recipe_label(handler: StationHandler) -> tuple[str, int]:
    """The selected recipe's name and version. The StationHandler seam gives only the number;
    a station (server.station.core.Station) also has ``active`` (name, version)."""
    active = getattr(handler, "active", None)
    if active is None:
        number = handler.selected_recipe()
        return (str(number) if number else "", 0)
    return active.config.name, int(active.version)


def _time(value: Any) -> datetime:
    if isinstance(value, datetime):
        return value
    if isinstance(value, str):
        try:
            return datetime.fromisoformat(value)
        except ValueError:
            pass
    return datetime.now(UTC)


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


if __name__ == "__main__":
    logging.basicConfig(level=logging.ERROR)
    for name, seconds in asyncio.run(load_times()).items():
        print(f"{name}: {seconds:.2f} s")
