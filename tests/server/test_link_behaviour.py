"""The link behaviour suite: one test class, run against every way a trigger reaches the station.

python-can's back-to-back pattern, as the cameras have it (tests/drivers/test_camera_behaviour.py):
:class:`LinkBehaviour` states what every link does with the real station (server.station.core,
a real store, simulated cameras), and each backend's subclass says only how its client speaks:
Modbus/TCP through the project's PLC twin, the same PLC program over EtherNet/IP class 1 I/O and
over S7 (the station polling a python-snap7 CPU's DBs), OPC UA through asyncua's client calling
the Machine Vision methods, and the REST trigger path (POST /api/v1/station/trigger through the
API app and the control channel). A backend that lacks a capability says so in ``lacks``, with
the reason; the test is then skipped naming it. A new fieldbus gets a subclass here before it
lands.

The stations are shared by every class (module scope): a fixed station with every link, a
robot-mounted one (views, flange poses) and one whose 2 ms deadline no trigger can meet.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import httpx
import numpy as np
import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.crypto.cert_gen import setup_self_signed_certificate
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography.x509.oid import ExtendedKeyUsageOID
from stations import ENGINEER, relaxed_deadline, runtime_options, settings_for, station_file

from drivers.links.codecs import int_scales
from drivers.links.layout import Command, Status, VerifyVerdict
from drivers.links.opcua import MV_URI, MVPOSE_URI
from drivers.links.opcua.settings import hash_password
from drivers.links.s7.twin import S7Cpu, S7Port
from drivers.links.twin import PlcTwin
from mvpose_core.reasons import Reason
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import RobotConvention, from_robot, to_robot, transform_error
from server.loopback import RunningServer, attach_twin, detach_twin, running_server
from server.store.schemas import MeasurementFilter, StoredMeasurement
from tests.drivers import profinet_peer
from tests.waiting import until

pytestmark = [pytest.mark.asyncio(loop_scope="module"), pytest.mark.timeout(600)]

CLIENT_URI = "urn:mvpose:test:link-behaviour"
PASSWORD = "operator-pw"


# --------------------------------------------------------------------------- the stations
@dataclass
class Env:
    """One running station (store, links, the API app on a free port) and what its clients
    need."""

    rs: RunningServer
    tmp: Path
    cert: tuple[Path, Path]  # an OPC UA client certificate the station trusts (key, cert)
    cpu: S7Cpu  # the S7 PLC the station's S7 link polls (python-snap7's server)

    @property
    def station(self) -> Any:
        return self.rs.runtime

    @property
    def recipe(self) -> Any:
        return self.station.active.config

    async def place(self, T_rf_from_pf: np.ndarray) -> None:
        """The simulated part at this pose (rendered before the next trigger)."""
        await asyncio.to_thread(self.station.scene.set_part_pose, T_rf_from_pf)

    async def record(self, result_id: int) -> StoredMeasurement:
        """The one stored record with seq ``result_id``."""
        await asyncio.to_thread(self.station.wait_idle)
        rows = list(self.station.services.store.measurements.iterate(
            MeasurementFilter(result_id=result_id)))
        assert [r.seq for r in rows] == [result_id]
        return rows[0]

    async def count(self) -> int:
        await asyncio.to_thread(self.station.wait_idle)
        return int(self.station.services.store.measurements.count())


def _links(tmp: Path, opcua: bool) -> Callable[[dict[str, Any]], None]:
    def edit(data: dict[str, Any]) -> None:
        # only this host's own loopback address may be the PLC (a peer from 127.0.0.2 is not)
        links = data.setdefault("links", {})
        links.setdefault("modbus", {})["allowlist"] = ["127.0.0.1"]
        links["enip"] = {"port": 0, "io_port": 0, "allowlist": ["127.0.0.1"],
                         "watchdog_s": 10.0}
        if opcua:
            links["opcua"] = {
                "port": 0, "pki_dir": str(tmp / "pki"), "measure_timeout_s": 30.0,
                "security": ["Basic256Sha256_SignAndEncrypt"], "query_spacing_s": 0.0,
                "users": {"olga": {"role": "operator",
                                   "password_hash": hash_password(PASSWORD, 10_000)}}}
    return edit


@contextlib.asynccontextmanager
async def _env(tmp: Path, name: str, *edits: Callable[[dict[str, Any]], None],
               opcua: bool = True) -> AsyncIterator[Env]:
    key, cert = tmp / "client.pem", tmp / "client.der"
    await setup_self_signed_certificate(key, cert, CLIENT_URI, socket.gethostname(),
                                        [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": "t"})
    (tmp / "pki" / "trusted").mkdir(parents=True)
    (tmp / "pki" / "trusted" / "client.der").write_bytes(cert.read_bytes())
    settings = settings_for(station_file(tmp, name, *edits, _links(tmp, opcua)), tmp / "var")
    with S7Cpu() as cpu:  # the S7 link is the client: its PLC runs before the station
        # polled every 20 ms, not 5: the CPU's server threads share this process's GIL with
        # every other link of the shared stations
        s7 = {**cpu.settings, "watchdog_s": 10.0, "poll_s": 0.02}
        async with running_server(settings, runtime_options(3), links={"s7": s7}) as rs:
            lk = rs.runtime.link("opcua")
            if lk is not None:  # the Machine Vision NodeSet loads in the background of the start
                assert await asyncio.to_thread(lk.started.wait, 120), lk.status()
            yield Env(rs, tmp, (key, cert), cpu)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def fixed(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
    """Station 1 (fixed cameras, one recipe) with Modbus, S7, OPC UA and the API."""
    async with _env(tmp_path_factory.mktemp("fixed"), "station1", relaxed_deadline) as env:
        yield env


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def mounted(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
    """The lab station: a stereo pair on the robot's flange, two views per part."""
    async with _env(tmp_path_factory.mktemp("mounted"), "lab", relaxed_deadline,
                    opcua=False) as env:
        yield env


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def hurried(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
    """Station 1 with a 2 ms deadline: less than any capture and detection of four frames."""
    def deadline(data: dict[str, Any]) -> None:
        data["deadline_ms"] = 2.0

    async with _env(tmp_path_factory.mktemp("hurried"), "station1", deadline) as env:
        yield env


# --------------------------------------------------------------------------- the behaviour
@dataclass(frozen=True)
class Answer:
    """A trigger's answer as the client read it, in the station's terms."""

    result_code: int
    result_id: int
    final: bool
    views_done: int
    offset: tuple[float, ...] | None  # the recipe's convention; None unless OK


@dataclass
class Verified:
    """A calibration verify's answer as the client read it."""

    code: int  # 0: measured and judged
    result_id: int  # the verify record's result id
    passed: bool
    difference: tuple[float, ...] | None  # 6-DoF difference to the taught pose (PLC form)
    displacement_mm: float
    rotation_deg: float


class LinkBehaviour:
    """What every link does; a subclass per backend says how its client speaks."""

    name: ClassVar[str]  # the backend's name in the station's status and records
    lacks: ClassVar[dict[str, str]] = {}  # case → why the backend does not have it

    def need(self, case: str) -> None:
        if case in self.lacks:
            pytest.skip(f"{self.name} has no {case}: {self.lacks[case]}")

    # ------------------------------------------------------------------ the client's side
    def session(self, env: Env) -> contextlib.AbstractAsyncContextManager[Any]:
        raise NotImplementedError

    async def trigger(self, s: Any, env: Env, trigger_id: int, part_id: str, view: int = 0,
                      pose: tuple[float, ...] | None = None) -> Answer:
        raise NotImplementedError

    async def select_recipe(self, s: Any, env: Env, number: int) -> None:
        """Select recipe ``number`` (asserting that the backend says it is done)."""
        raise NotImplementedError

    async def refuse_unknown_recipe(self, s: Any, env: Env) -> None:
        """Ask for a recipe the station does not have; assert the refusal and its code."""
        raise NotImplementedError

    async def teach(self, s: Any, env: Env) -> None:
        """Arm the teach: the next final OK result becomes the zero offset."""
        raise NotImplementedError

    async def refuse_stranger(self, env: Env) -> None:
        """A peer the link must not serve (allowlist, security, role) is refused."""
        raise NotImplementedError

    async def verify(self, s: Any, env: Env) -> Verified:
        """Run a calibration verify: the reference part measured now and judged."""
        raise NotImplementedError

    # ------------------------------------------------------------------ the cases
    async def test_a_trigger_is_answered_ok_with_the_records_seq(self, fixed: Env) -> None:
        await fixed.place(fixed.recipe.T_rf_from_pf0.matrix)
        async with self.session(fixed) as s:
            a = await self.trigger(s, fixed, 11, f"VIN-{self.name}")
        assert (a.result_code, a.final) == (0, True) and a.result_id > 0, a
        stored = await fixed.record(a.result_id)
        rec = stored.record
        assert (rec.trigger_id, rec.part_id, rec.reason_code) == (11, f"VIN-{self.name}", 0)
        assert a.offset is not None and rec.offset is not None
        # Modbus carries float32 (1e-3 mm / 1e-4 deg); the others carry the record's doubles
        np.testing.assert_allclose(a.offset, rec.offset.values, atol=1e-3)

    async def test_ids_are_never_reused(self, fixed: Env) -> None:
        await fixed.place(fixed.recipe.T_rf_from_pf0.matrix)
        async with self.session(fixed) as s:
            # the same trigger id three times (a PLC's counter after its restart): three records
            answers = [await self.trigger(s, fixed, 7, f"SAME-{k}") for k in range(3)]
        ids = [a.result_id for a in answers]
        assert all(a.result_code == 0 for a in answers), answers
        assert ids == sorted(set(ids)) and len(ids) == 3, ids
        for k, rid in enumerate(ids):
            rec = (await fixed.record(rid)).record
            assert (rec.trigger_id, rec.part_id) == (7, f"SAME-{k}")

    async def test_views_of_a_robot_mounted_recipe(self, mounted: Env) -> None:
        self.need("views")
        st = mounted.station
        views = [v.id for v in st.station.views]
        assert views == [1, 2]
        await mounted.place(mounted.recipe.T_rf_from_pf0.matrix)
        async with self.session(mounted) as s:
            answers = []
            for view in views:
                st.scene.set_view(view, st.station.view(view).T_rf_from_gf.matrix)
                answers.append(await self.trigger(s, mounted, 30, "VIEWS", view=view))
        first, last = answers
        assert (first.result_code, first.final, first.views_done, first.result_id) == (
            0, False, 1, 0), first
        assert (last.result_code, last.final, last.views_done) == (0, True, 2), last
        rec = (await mounted.record(last.result_id)).record
        assert {d.view for d in rec.detections} == {1, 2}

    async def test_the_robots_flange_pose_reaches_the_record(self, mounted: Env) -> None:
        self.need("robot pose")
        st = mounted.station
        conv = mounted.recipe.robot_convention
        rng = np.random.default_rng(17)
        await mounted.place(mounted.recipe.T_rf_from_pf0.matrix)
        sent = {}
        async with self.session(mounted) as s:
            for view in (1, 2):
                # the robot stops 2 mm / 0.2° off the taught view pose, and says so
                actual = st.station.view(view).T_rf_from_gf.matrix @ random_displacement(
                    rng, 2.0, 0.2)
                st.scene.set_view(view, actual)
                sent[view] = actual
                a = await self.trigger(s, mounted, 40 + view, "POSE", view=view,
                                       pose=tuple(to_robot(actual, conv)))
        assert a.result_code == 0 and a.final, a
        rec = (await mounted.record(a.result_id)).record
        got = {f.view: np.array(f.T_rf_from_gf) for f in rec.flange_poses or []}
        assert sorted(got) == [1, 2]
        for view, T in sent.items():
            deg, mm = transform_error(got[view], T)
            assert deg < 1e-3 and mm < 2e-3, (view, deg, mm)  # 1 µm and 1e-4° on the wire

    async def test_teach_makes_the_next_ok_the_zero_offset(self, fixed: Env) -> None:
        self.need("teach")
        recipe = fixed.recipe
        tol = recipe.tolerances
        version = fixed.station.active.version
        await fixed.place(recipe.T_rf_from_pf0.matrix @ random_displacement(
            np.random.default_rng(5), 15.0, 1.5))
        async with self.session(fixed) as s:
            await self.teach(s, fixed)
            taught = await self.trigger(s, fixed, 50, "TEACH")
            again = await self.trigger(s, fixed, 51, "TAUGHT")
        assert taught.result_code == 0 and again.result_code == 0, (taught, again)
        assert fixed.station.active.version == version + 1  # a new version, the new reference
        assert (await fixed.record(again.result_id)).record.recipe_version == version + 1
        assert again.offset is not None
        T = from_robot(again.offset, recipe.robot_convention)
        deg, mm = transform_error(T, np.eye(4))
        assert mm < tol.translation_mm / 2 and deg < tol.rotation_deg / 2, (mm, deg)

    async def test_verify_measures_the_reference_part_and_records_it(self, fixed: Env) -> None:
        self.need("verify")
        recipe = fixed.recipe  # the active version's taught pose (a teach may have moved it)
        tol = recipe.tolerances
        await fixed.place(recipe.T_rf_from_pf0.matrix)
        async with self.session(fixed) as s:
            good = await self.verify(s, fixed)
            # the part 3 limits off its taught place along its X axis: FAIL, by that much
            moved = np.eye(4)
            moved[0, 3] = 3 * tol.translation_mm
            await fixed.place(recipe.T_rf_from_pf0.matrix @ moved)
            bad = await self.verify(s, fixed)
        assert (good.code, good.passed) == (0, True) and good.result_id > 0, good
        assert good.difference is not None and len(good.difference) == 6
        assert good.displacement_mm < tol.translation_mm / 2, good
        assert (bad.code, bad.passed) == (0, False) and bad.result_id > good.result_id, bad
        assert bad.displacement_mm == pytest.approx(3 * tol.translation_mm, abs=0.05), bad
        assert bad.difference is not None
        assert float(np.linalg.norm(bad.difference[:3])) == pytest.approx(
            3 * tol.translation_mm, abs=0.05)
        for v in (good, bad):  # each verify is a record of the audit trail
            rec = (await fixed.record(v.result_id)).record
            assert (rec.part_id, rec.trigger_id) == ("VERIFY", 0), rec

    async def test_recipe_select_and_an_unknown_recipe_refused(self, fixed: Env) -> None:
        number = fixed.station.active.number
        async with self.session(fixed) as s:
            await self.select_recipe(s, fixed, number)
            assert fixed.station.selected_recipe() == number
            await self.refuse_unknown_recipe(s, fixed)
            assert fixed.station.selected_recipe() == number  # nothing changed
            await fixed.place(fixed.recipe.T_rf_from_pf0.matrix)
            a = await self.trigger(s, fixed, 60, "AFTER-SELECT")
        assert a.result_code == 0, a

    async def test_a_trigger_past_the_deadline_is_answered_and_recorded(
            self, hurried: Env) -> None:
        await hurried.place(hurried.recipe.T_rf_from_pf0.matrix)
        async with self.session(hurried) as s:
            a = await self.trigger(s, hurried, 70, "LATE")
        assert a.final and a.offset is None and a.result_id > 0
        rec = (await hurried.record(a.result_id)).record
        assert (rec.trigger_id, rec.result, rec.reason_code) == (70, "NOK", a.result_code)
        if a.result_code == Reason.CAMERA_FAILED:
            # on a busy machine the 2 ms budget can end before the simulated cameras answer:
            # then the grab itself is what ran out of time, and the record says so
            assert "no answer within" in (rec.message or ""), rec.message
        else:
            assert a.result_code in (Reason.DEADLINE_EXCEEDED, Reason.TIMEOUT), a

    async def test_the_link_stays_up_across_a_client_that_goes_and_comes_back(
            self, fixed: Env) -> None:
        self.need("connection")
        link = fixed.station.link(self.name)
        await fixed.place(fixed.recipe.T_rf_from_pf0.matrix)
        async with self.session(fixed) as s:
            before = await self.trigger(s, fixed, 80, "BEFORE")
        assert link.ready() and link.status()["running"]  # the client went; the link did not
        assert fixed.station.readiness()["links"]
        async with self.session(fixed) as s:
            after = await self.trigger(s, fixed, 81, "AFTER")
        assert (before.result_code, after.result_code) == (0, 0), (before, after)
        assert after.result_id > before.result_id
        assert fixed.station.status()["links"][self.name]["running"]

    async def test_a_stranger_is_refused(self, fixed: Env) -> None:
        before = await fixed.count()
        await self.refuse_stranger(fixed)
        assert await fixed.count() == before  # nothing measured, nothing recorded


# --------------------------------------------------------------------------- Modbus/TCP
class TestModbus(LinkBehaviour):
    """The PLC handshake over Modbus/TCP, driven by the project's PLC twin."""

    name = "modbus"

    @contextlib.asynccontextmanager
    async def session(self, env: Env) -> AsyncIterator[PlcTwin]:
        twin, beat = await attach_twin(env.station.link_port("modbus"), 0.002)
        try:
            yield twin
        finally:
            await detach_twin(twin, beat)

    async def trigger(self, s: PlcTwin, env: Env, trigger_id: int, part_id: str, view: int = 0,
                      pose: tuple[float, ...] | None = None) -> Answer:
        counts = None
        if pose is not None:
            conv = env.recipe.robot_convention
            assert conv is not RobotConvention.ABB  # the PLC form is the pose itself
            counts = [round(v * k) for v, k in zip(pose, int_scales(conv), strict=True)]
        st = await s.cycle(trigger_id, view, pose_counts=counts, part_id=part_id, timeout=10.0)
        final = st.has(Status.RESULT_VALID)
        assert final != st.has(Status.VIEW_DONE), st
        ok = final and st.has(Status.RESULT_OK)
        return Answer(st.result_code, st.result_id if final else 0, final, st.views_done,
                      tuple(st.offset_float) if ok else None)

    async def select_recipe(self, s: PlcTwin, env: Env, number: int) -> None:
        done = await s.command(Command.SELECT_RECIPE, number)
        assert done.has(Status.COMMAND_DONE) and done.recipe == number, done

    async def refuse_unknown_recipe(self, s: PlcTwin, env: Env) -> None:
        failed = await s.command(Command.SELECT_RECIPE, 999)
        assert failed.has(Status.COMMAND_FAILED)
        assert failed.command_result == Reason.UNKNOWN_RECIPE

    async def teach(self, s: PlcTwin, env: Env) -> None:
        done = await s.command(Command.TEACH_REFERENCE)
        assert done.has(Status.COMMAND_DONE), done

    async def verify(self, s: PlcTwin, env: Env) -> Verified:
        st = await s.command(Command.VERIFY, timeout=30.0)
        judged = st.has(Status.COMMAND_DONE)
        assert judged == (st.verify_verdict is not VerifyVerdict.NONE), st
        return Verified(st.command_result, st.verify_result_id,
                        st.verify_verdict is VerifyVerdict.PASSED,
                        st.verify_difference if judged else None, st.verify_displacement_mm,
                        st.verify_rotation_deg)

    async def refuse_stranger(self, env: Env) -> None:
        """The allowlist: a peer from 127.0.0.2 is closed without an answer."""
        link = env.station.link("modbus")
        rejected = link.status()["rejected_connections"]
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", env.station.link_port("modbus"), local_addr=("127.0.0.2", 0))
        try:
            writer.write(b"\x00\x01\x00\x00\x00\x06\x01\x04\x00\x00\x00\x02")  # fc 4, 2 regs
            try:  # closed without an answer: an end of stream, or a reset (our request unread)
                await writer.drain()
                assert await asyncio.wait_for(reader.read(100), 10) == b""
            except ConnectionResetError:
                pass
        finally:
            writer.close()
        # the link runs in a child process: its counts come with the child's status reports
        await until(lambda: link.status()["rejected_connections"] == rejected + 1,
                    "the refused connection counted")


# --------------------------------------------------------------------------- EtherNet/IP
class TestEnip(TestModbus):
    """The same handshake over EtherNet/IP class 1 I/O (RPI 4 ms), driven by the PLC twin's
    scanner port (drivers/links/enip/twin.py); the PLC program's steps are Modbus's."""

    name = "enip"

    @contextlib.asynccontextmanager
    async def session(self, env: Env) -> AsyncIterator[PlcTwin]:
        twin, beat = await attach_twin(env.station.link_port("enip"), 0.002, link="enip")
        try:
            yield twin
        finally:
            await detach_twin(twin, beat)

    async def refuse_stranger(self, env: Env) -> None:
        """The allowlist: a scanner from 127.0.0.2 is closed without an answer."""
        link = env.station.link("enip")
        rejected = link.status()["rejected_peers"]
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", env.station.link_port("enip"), local_addr=("127.0.0.2", 0))
        try:  # RegisterSession (Vol 2, 2-4.4)
            writer.write(bytes.fromhex("6500040000000000000000000000000000000000000000000100"
                                       "0000"))
            try:
                await writer.drain()
                assert await asyncio.wait_for(reader.read(100), 10) == b""
            except ConnectionResetError:
                pass
        finally:
            writer.close()
        assert link.status()["rejected_peers"] == rejected + 1


# --------------------------------------------------------------------------- Siemens S7
class TestS7(TestModbus):
    """The same PLC program over S7 PUT/GET: the station's S7 link polls the trigger DB of a
    CPU (python-snap7's server) and writes its result DB; the twin runs on the CPU's DBs."""

    name = "s7"
    lacks: ClassVar[dict[str, str]] = {
        "stranger": "mvpose is the S7 client: it connects only to the PLC its station file "
                    "names, so there is no peer to refuse (no allowlist; docs/integration.md)"}

    @contextlib.asynccontextmanager
    async def session(self, env: Env) -> AsyncIterator[PlcTwin]:
        twin, beat = await attach_twin(S7Port(env.cpu), 0.002)
        try:
            yield twin
        finally:
            await detach_twin(twin, beat)

    async def refuse_stranger(self, env: Env) -> None:
        self.need("stranger")


# --------------------------------------------------------------------------- PROFINET
PN_NAME = "mvpose-station"


def _profinet(net: profinet_peer.Net) -> Callable[[dict[str, Any]], None]:
    def edit(data: dict[str, Any]) -> None:
        data.setdefault("links", {})["profinet"] = {
            "interface": net.device_if, "station_name": PN_NAME, "rpc_host": net.device_ip,
            "watchdog_s": 10.0}
    return edit


@pytest.mark.skipif(profinet_peer.usable() is not None, reason=str(profinet_peer.usable()))
class TestProfinet(TestModbus):
    """The same handshake over PROFINET cyclic data (RT_CLASS_1, 4 ms), the station an
    IO-device on a veth pair and profinet-py the IO-controller in a namespace of its own; the
    PLC program's steps are Modbus's. The class's stations are its own (they need the veth)."""

    name = "profinet"
    nets: ClassVar[dict[int, profinet_peer.Net]] = {}

    @classmethod
    @contextlib.asynccontextmanager
    async def _station(cls, tmp: Path, k: int, name: str,
                       *edits: Callable[[dict[str, Any]], None]) -> AsyncIterator[Env]:
        with profinet_peer.veth(k) as net:
            async with _env(tmp, name, *edits, _profinet(net), opcua=False) as env:
                cls.nets[id(env.rs)] = net
                yield env

    @pytest_asyncio.fixture(scope="class", loop_scope="module")
    @classmethod
    async def fixed(cls, tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
        async with cls._station(tmp_path_factory.mktemp("pn-fixed"), 1, "station1",
                                 relaxed_deadline) as env:
            yield env

    @pytest_asyncio.fixture(scope="class", loop_scope="module")
    @classmethod
    async def mounted(cls, tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
        async with cls._station(tmp_path_factory.mktemp("pn-mounted"), 2, "lab",
                                 relaxed_deadline) as env:
            yield env

    @pytest_asyncio.fixture(scope="class", loop_scope="module")
    @classmethod
    async def hurried(cls, tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
        def deadline(data: dict[str, Any]) -> None:
            data["deadline_ms"] = 2.0

        async with cls._station(tmp_path_factory.mktemp("pn-hurried"), 3, "station1",
                                 deadline) as env:
            yield env

    @contextlib.asynccontextmanager
    async def session(self, env: Env) -> AsyncIterator[PlcTwin]:
        async with profinet_peer.controller(self.nets[id(env.rs)]) as ctl:
            await ctl.run_ar(PN_NAME, reduction_ratio=4)  # 4 ms
            try:
                async with profinet_peer.plc(ctl, ready=True) as twin:
                    yield twin
            finally:
                await ctl("stop_cyclic")
                await ctl("release")

    async def refuse_stranger(self, env: Env) -> None:
        """A supervisor's device-access AR (no IO, no AlarmCR) is refused: the device serves
        one IO controller's IOCARSingle."""
        link = env.station.link("profinet")
        refused = link.status()["refused_connects"]
        async with profinet_peer.controller(self.nets[id(env.rs)]) as ctl:
            answer = await ctl("connect_supervisor", name=PN_NAME)
        assert not answer["ok"] and "rejected" in answer["error"], answer
        await until(lambda: link.status()["refused_connects"] == refused + 1,
                    "the refused Connect counted")


# --------------------------------------------------------------------------- OPC UA
class TestOpcUa(LinkBehaviour):
    """The Machine Vision server (OPC 40100-1), called by asyncua's client."""

    name = "opcua"
    lacks: ClassVar[dict[str, str]] = {
        "views": "mvpose's Measure method and StartSingleJob take no view index (a "
                 "robot-mounted rig is triggered over the PLC's fieldbus)",
        "robot pose": "no method of the Machine Vision model carries the flange pose",
        "teach": "OPC 40100-1 has no teach method; the reference is taught over Modbus or REST",
    }

    async def _client(self, env: Env, user: str, password: str) -> Client:
        key, cert = env.cert
        port = env.station.link_port("opcua")
        client = Client(f"opc.tcp://127.0.0.1:{port}/mvpose", timeout=15, watchdog_intervall=15)
        client.application_uri = CLIENT_URI
        await client.set_security(SecurityPolicyBasic256Sha256, certificate=str(cert),
                                  private_key=str(key),
                                  mode=ua.MessageSecurityMode.SignAndEncrypt)
        client.set_user(user)
        client.set_password(password)
        await client.connect()
        return client

    @contextlib.asynccontextmanager
    async def session(self, env: Env) -> AsyncIterator[tuple[Client, Any, int, int]]:
        client = await self._client(env, "olga", PASSWORD)
        try:
            await client.load_data_type_definitions()
            mv = await client.get_namespace_index(MV_URI)
            own = await client.get_namespace_index(MVPOSE_URI)
            vs = await client.nodes.objects.get_child(f"{mv}:VisionSystem")
            yield client, vs, mv, own
        finally:
            await client.disconnect()

    async def trigger(self, s: Any, env: Env, trigger_id: int, part_id: str, view: int = 0,
                      pose: tuple[float, ...] | None = None) -> Answer:
        assert view == 0 and pose is None
        _, vs, _, own = s
        rid, code, offset, _s_mm, _s_deg = await vs.call_method(
            f"{own}:Measure", ua.Variant(part_id, ua.VariantType.String),
            ua.Variant(0, ua.VariantType.UInt16), ua.Variant(trigger_id, ua.VariantType.UInt32))
        return Answer(code, rid, True, 1, tuple(offset) if offset else None)

    async def verify(self, s: Any, env: Env) -> Verified:
        _, vs, _, own = s
        rid, code, passed, difference, mm, deg, message = await vs.call_method(f"{own}:Verify")
        assert isinstance(message, str) and message, message
        return Verified(code, rid, passed, tuple(difference) if difference else None, mm, deg)

    async def _prepare(self, s: Any, number: int) -> int:
        _, vs, mv, _ = s
        rm = await vs.get_child(f"{mv}:RecipeManagement")
        _, _, code = await rm.call_method(
            f"{mv}:PrepareRecipe", ua.RecipeIdExternalDataType(Id=str(number)),
            ua.RecipeIdInternalDataType(Id=""))
        return int(code)

    async def select_recipe(self, s: Any, env: Env, number: int) -> None:
        assert await self._prepare(s, number) == 0

    async def refuse_unknown_recipe(self, s: Any, env: Env) -> None:
        assert await self._prepare(s, 999) == Reason.UNKNOWN_RECIPE

    async def refuse_stranger(self, env: Env) -> None:
        """Security: a user the station file does not know, or a wrong password."""
        for user, password in (("mallory", PASSWORD), ("olga", "wrong")):
            with pytest.raises(ua.UaError) as err:
                client = await self._client(env, user, password)
                await client.disconnect()
            assert "BadUserAccessDenied" in repr(err.value) or "BadIdentityToken" in repr(
                err.value)


# --------------------------------------------------------------------------- REST
class TestRest(LinkBehaviour):
    """The commissioning trigger: POST /api/v1/station/trigger through the API app (uvicorn,
    in this process) and the control channel to the station."""

    name = "rest"
    lacks: ClassVar[dict[str, str]] = {
        "robot pose": "the trigger body has no flange pose (a robot reports it over its "
                      "fieldbus)",
        "connection": "REST holds no connection of its own: each request stands alone (the "
                      "API process's restart is tests/server/test_processes.py's subject)",
    }

    @contextlib.asynccontextmanager
    async def session(self, env: Env) -> AsyncIterator[httpx.AsyncClient]:
        async with httpx.AsyncClient(base_url=f"{env.rs.base_url}/api/v1", timeout=30,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            yield api

    async def trigger(self, s: httpx.AsyncClient, env: Env, trigger_id: int, part_id: str,
                      view: int = 0, pose: tuple[float, ...] | None = None) -> Answer:
        assert pose is None
        r = await s.post("/station/trigger", json={"part_id": part_id, "view": view,
                                                   "trigger_id": trigger_id})
        assert r.status_code == 200, r.text
        out = r.json()
        offset = out["offset"]
        return Answer(out["result_code"], out["result_id"], out["final"], out["views_done"],
                      tuple(offset) if offset is not None else None)

    async def select_recipe(self, s: httpx.AsyncClient, env: Env, number: int) -> None:
        name = env.station.book.by_number(number).config.name
        r = await s.post("/station/recipe", json={"name": name})
        assert r.status_code == 200 and r.json()["number"] == number, r.text

    async def refuse_unknown_recipe(self, s: httpx.AsyncClient, env: Env) -> None:
        r = await s.post("/station/recipe", json={"name": "no_such_recipe"})
        assert r.status_code == 404 and "no_such_recipe" in r.text, r.text

    async def teach(self, s: httpx.AsyncClient, env: Env) -> None:
        r = await s.post("/station/teach")
        assert r.status_code == 200 and r.json()["armed"], r.text

    async def verify(self, s: httpx.AsyncClient, env: Env) -> Verified:
        r = await s.post("/calibration/verify")
        assert r.status_code == 200, r.text
        out = r.json()
        return Verified(0, out["result_id"], out["passed"], tuple(out["offset"]["values"]),
                        out["grasp_displacement_mm"], out["rotation_deg"])

    async def refuse_stranger(self, env: Env) -> None:
        """The token's role: a read token may look, not trigger."""
        async with self.session(env) as api:
            made = await api.post("/tokens", json={"name": "reader", "role": "read"})
            assert made.status_code == 201, made.text
            read = {"Authorization": f"Bearer {made.json()['token']}"}
            r = await api.post("/station/trigger", json={"part_id": "X"}, headers=read)
            assert r.status_code == 403, r.text
            assert (await api.get("/station/status", headers=read)).status_code == 200

