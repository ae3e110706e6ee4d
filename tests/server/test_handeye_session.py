"""The robot-driven hand-eye end to end on the simulated lab station, over every link.

``mvpose calibrate synthetic`` renders the board from the station's stereo rig at flange poses
with a robot error; the test plays the robot with :mod:`server.handeye_rehearsal` (as ``mvpose
calibrate rehearse-handeye`` does): it shows the station's simulated cameras a pose's images
and sends that pose's recorded flange pose with the add, as a robot program does. Each link
drives begin / add / calculate, the refusals answer with their codes, and the result is a
calibration version waiting for activation whose hand-eye is as close to the synthetic truth
as ``mvpose calibrate handeye`` gets on the same images.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from stations import ENGINEER, relaxed_deadline, runtime_options, settings_for, station_file

from drivers.links.layout import Status
from drivers.links.opcua import MV_URI, MVPOSE_URI
from drivers.links.opcua.settings import hash_password
from mvpose_core.calibration.files import CalibrationFile, load_calibration
from mvpose_core.calibration.session import HandEyeCode
from server.cli import main
from server.commands.rehearsal import scale_cameras
from server.handeye_rehearsal import PlcHandEye, RehearsalSet, show_pose
from server.loopback import RunningServer, attach_twin, detach_twin, running_server

pytestmark = [pytest.mark.asyncio(loop_scope="module"), pytest.mark.timeout(900)]

BOARD = "charuco:15x11:40:30"
CLIENT_URI = "urn:mvpose:test:handeye"
PASSWORD = "engineer-pw"
SAMPLES = 12


def _half_size_with_board(data: dict[str, Any]) -> None:
    """The lab's cameras at half resolution (a quarter of the rendering and detection), and
    the calibration board the station's hand-eye sessions look at."""
    scale_cameras(data, 0.5)
    data["calibration_board"] = BOARD


def _links(tmp: Path) -> Callable[[dict[str, Any]], None]:
    def edit(data: dict[str, Any]) -> None:
        data.setdefault("links", {})["enip"] = {"port": 0, "io_port": 0,
                                                "allowlist": ["127.0.0.1"], "watchdog_s": 10.0}
        data["links"]["opcua"] = {
            "port": 0, "pki_dir": str(tmp / "pki"), "measure_timeout_s": 30.0,
            "security": ["Basic256Sha256_SignAndEncrypt"], "query_spacing_s": 0.0,
            "users": {"erik": {"role": "engineer",
                               "password_hash": hash_password(PASSWORD, 10_000)},
                      "olga": {"role": "operator",
                               "password_hash": hash_password(PASSWORD, 10_000)}}}
    return edit


@dataclass
class Env:
    rs: RunningServer
    tmp: Path
    cert: tuple[Path, Path]  # an OPC UA client certificate the station trusts (key, cert)
    set: RehearsalSet
    cli_error: tuple[float, float]  # mvpose calibrate handeye on the same images

    @property
    def station(self) -> Any:
        return self.rs.runtime

    async def show(self, sid: str | None) -> None:
        """The robot is at pose ``sid``: the rig's cameras see its images (None: no board)."""
        await asyncio.to_thread(show_pose, self.station, self.set, sid)

    def stored(self, version: int) -> tuple[bool, CalibrationFile]:
        store = self.station.services.store
        info, content = store.versions.content("calibration", self.station.station.name, version)
        return info.active, CalibrationFile.model_validate(content)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def env(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
    tmp = tmp_path_factory.mktemp("handeye")
    key, cert = tmp / "client.pem", tmp / "client.der"
    await setup_self_signed_certificate(key, cert, CLIENT_URI, socket.gethostname(),
                                        [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "t"})
    (tmp / "pki" / "trusted").mkdir(parents=True)
    (tmp / "pki" / "trusted" / "client.der").write_bytes(cert.read_bytes())
    path = station_file(tmp, "lab", relaxed_deadline, _half_size_with_board, _links(tmp))
    root = tmp / "rehearsal"
    code = await asyncio.to_thread(main, [
        "calibrate", "synthetic", "--station", str(path), "--out", str(root), "--board", BOARD,
        "--samples", str(SAMPLES), "--robot-error", "0.05", "0.01", "--seed", "5",
        "--no-progress"])
    assert code == 0
    rehearsal = RehearsalSet.load(root)
    out = tmp / "cli" / "handeye.json"
    code = await asyncio.to_thread(main, [
        "calibrate", "handeye", "--images", str(root / "images"), "--board", BOARD,
        "--poses", str(root / "poses.csv"), "--convention", "fanuc", "--station", str(path),
        "--out", str(out), "--no-progress"])
    assert code == 0
    cli_error = rehearsal.error(load_calibration(out))
    async with running_server(settings_for(path, tmp / "var"), runtime_options(3)) as rs:
        lk = rs.runtime.link("opcua")  # the Machine Vision NodeSet loads in the background
        assert await asyncio.to_thread(lk.started.wait, 120), lk.status()
        yield Env(rs, tmp, (key, cert), rehearsal, cli_error)


# --------------------------------------------------------------------------- one session
Step = Callable[..., Awaitable[tuple[int, dict[str, Any]]]]


async def run_session(env: Env, begin: Step, add: Step, calculate: Step,
                      holdout: int) -> dict[str, Any]:
    """Every refusal a robot program meets, then a whole session: the calculate's answer."""
    if not env.station.handeye.status()["active"]:  # the module's first session
        code, _ = await add(env.set.poses["001"])
        assert code == HandEyeCode.NO_SESSION
    code, _ = await begin(holdout)  # drops the session before, if any
    assert code == 0
    code, out = await calculate()
    assert code == HandEyeCode.TOO_FEW_POSES, out
    await env.show(None)
    code, out = await add(env.set.poses["001"])
    assert code == HandEyeCode.BOARD_NOT_FOUND and out["pose"] == 1, out
    metres = [v / 1000 if k < 3 else v for k, v in enumerate(env.set.poses["001"])]
    code, out = await add(metres)
    assert code == HandEyeCode.UNIT_SUSPICIOUS and out["poses"] == 0, out
    for k, (sid, pose) in enumerate(env.set.poses.items()):
        await env.show(sid)
        code, out = await add(pose)
        assert code == 0 and out["poses"] == k + 1, out
    code, out = await calculate()
    assert code == 0, out
    return out


def check_result(env: Env, out: dict[str, Any], holdout: int) -> CalibrationFile:
    active, calib = env.stored(out["version"])
    assert not active  # waiting for an engineer's activation
    assert calib.kind == "handeye" and calib.station == env.station.station.name
    assert len(calib.report["hold-out"]) == holdout
    assert len(calib.inputs.samples_used) == SAMPLES - holdout
    deg, mm = env.set.error(calib)
    cli_deg, cli_mm = env.cli_error
    # the station's session holds the station's intrinsics, the command estimated its own
    assert mm <= max(1.5 * cli_mm, 0.3) and deg <= max(1.5 * cli_deg, 0.03), \
        (mm, deg, env.cli_error)
    # the held-out poses: their reprojection carries the robot's pose error (0.01° at 1.7 m is
    # about 0.5 px here), their implied flange pose one image's PnP error along the lens axis
    assert 0 < out["sigma_mm"] < 2.0 and 0 < out["holdout_rms_px"] < 2.0, out
    assert out["holdout_mm"] < 3.0 and out["holdout_deg"] < 0.2, out
    return calib


# --------------------------------------------------------------------------- REST
@contextlib.asynccontextmanager
async def rest(env: Env) -> AsyncIterator[httpx.AsyncClient]:
    async with httpx.AsyncClient(base_url=f"{env.rs.base_url}/api/v1", timeout=300,
                                 headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
        yield api


def _rest_answer(r: httpx.Response) -> tuple[int, dict[str, Any]]:
    body = r.json()
    if r.status_code == 409:
        return body["code"], body
    assert r.status_code == 200, r.text
    return body["code"], body


async def test_rest_session_stores_a_version_waiting_for_activation(env: Env) -> None:
    async with rest(env) as api:
        r = await api.get("/calibration/handeye")
        assert r.status_code == 200 and r.json()["session"]["active"] is False, r.text

        async def begin(holdout: int) -> tuple[int, dict[str, Any]]:
            return _rest_answer(await api.post("/calibration/handeye/begin",
                                               json={"holdout": holdout}))

        async def add(pose: list[float]) -> tuple[int, dict[str, Any]]:
            return _rest_answer(await api.post("/calibration/handeye/poses", json={"pose": pose}))

        async def calculate() -> tuple[int, dict[str, Any]]:
            return _rest_answer(await api.post("/calibration/handeye/calculate"))

        out = await run_session(env, begin, add, calculate, holdout=3)
        calib = check_result(env, out, 3)
        status = (await api.get("/calibration/handeye")).json()
        assert status["session"]["poses"] == SAMPLES and status["version"] == out["version"]
        folder = Path(status["session"]["folder"])
        assert "hold-out: 3 poses" in (folder / "report.txt").read_text()
        assert len(list((folder / "left").glob("*.png"))) == SAMPLES
        assert (folder / "poses.csv").read_text().count("\n") == SAMPLES + 1
        # a reader may look, not calibrate
        made = await api.post("/tokens", json={"name": "reader", "role": "read"})
        read = {"Authorization": f"Bearer {made.json()['token']}"}
        r = await api.post("/calibration/handeye/begin", headers=read)
        assert r.status_code == 403, r.text
        # the engineer activates it: the station measures with it
        r = await api.post(f"/calibrations/{env.station.station.name}/versions/"
                           f"{out['version']}/activate")
        assert r.status_code == 200 and r.json()["active"], r.text
        assert calib.sha256 == env.stored(out["version"])[1].sha256


# --------------------------------------------------------------------------- OPC UA
FIELDS = ("code", "poses", "pose", "version", "sigma_mm", "sigma_deg", "holdout_rms_px",
          "holdout_mm", "holdout_deg", "message")


@contextlib.asynccontextmanager
async def opcua(env: Env, user: str) -> AsyncIterator[tuple[Any, int]]:
    key, cert = env.cert
    port = env.station.link_port("opcua")
    client = Client(f"opc.tcp://127.0.0.1:{port}/mvpose", timeout=300, watchdog_intervall=15)
    client.application_uri = CLIENT_URI
    await client.set_security(SecurityPolicyBasic256Sha256, certificate=str(cert),
                              private_key=str(key), mode=ua.MessageSecurityMode.SignAndEncrypt)
    client.set_user(user)
    client.set_password(PASSWORD)
    await client.connect()
    try:
        mv = await client.get_namespace_index(MV_URI)
        own = await client.get_namespace_index(MVPOSE_URI)
        yield await client.nodes.objects.get_child(f"{mv}:VisionSystem"), own
    finally:
        await client.disconnect()


async def test_opcua_methods_drive_a_session(env: Env) -> None:
    async with opcua(env, "olga") as (vs, own):  # an operator may not calibrate
        with pytest.raises(ua.UaError) as err:
            await vs.call_method(f"{own}:HandEyeBegin", ua.Variant(2, ua.VariantType.UInt16))
        assert "BadUserAccessDenied" in repr(err.value), err.value
    async with opcua(env, "erik") as (vs, own):
        async def call(method: str, *args: ua.Variant) -> tuple[int, dict[str, Any]]:
            out = dict(zip(FIELDS, await vs.call_method(f"{own}:{method}", *args), strict=True))
            assert isinstance(out["message"], str) and out["message"], out
            return out["code"], out

        async def begin(holdout: int) -> tuple[int, dict[str, Any]]:
            return await call("HandEyeBegin", ua.Variant(holdout, ua.VariantType.UInt16))

        async def add(pose: list[float]) -> tuple[int, dict[str, Any]]:
            return await call("HandEyeAddPose", ua.Variant(pose, ua.VariantType.Double))

        async def calculate() -> tuple[int, dict[str, Any]]:
            return await call("HandEyeCalculate")

        out = await run_session(env, begin, add, calculate, holdout=2)
        check_result(env, out, 2)


# --------------------------------------------------------------------------- the PLC's fieldbus
@pytest.mark.parametrize("link", ["modbus", "enip"])
async def test_plc_commands_drive_a_session(env: Env, link: str) -> None:
    """The robot program's sequence through the PLC, over Modbus/TCP and EtherNet/IP class 1
    I/O (the handshake is the same on every cyclic bus): HANDEYE_BEGIN, HANDEYE_ADD_POSE with
    the pose in the robot pose words (ROBOT_POSE_VALID), HANDEYE_CALCULATE; every answer in the
    command result word and the hand-eye block."""
    twin, beat = await attach_twin(env.station.link_port(link), 0.002, link=link)
    plc = PlcHandEye(twin, env.set.convention)

    try:
        # without ROBOT_POSE_VALID an add has no pose: refused, nothing kept
        await plc.begin(2)
        code, out = await plc.add(None)
        assert code == HandEyeCode.BAD_POSE and out["poses"] == 0, out
        out = await run_session(env, plc.begin, plc.add, plc.calculate, holdout=2)
        check_result(env, out, 2)
        # the station's trigger handshake still works after the session
        assert (await twin.read_status()).has(Status.READY)
    finally:
        await detach_twin(twin, beat)
