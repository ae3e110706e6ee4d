"""The robot-driven hand-eye end to end on the simulated lab station, over every link.

``mvpose calibrate synthetic`` renders the board from the station's stereo rig at flange poses
with a robot error; the test plays the robot: it shows the station's simulated cameras a
pose's images (``SimScene.set_frames``) and sends that pose's recorded flange pose with the
add, as a robot program does. Each link drives begin / add / calculate, the refusals answer
with their codes, and the result is a calibration version waiting for activation whose
hand-eye is as close to the synthetic truth as ``mvpose calibrate handeye`` gets on the same
images.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
import pytest_asyncio
from stations import ENGINEER, relaxed_deadline, runtime_options, settings_for, station_file

from mvpose_core.calibration.files import CalibrationFile, load_calibration
from mvpose_core.calibration.session import HandEyeCode
from mvpose_core.transforms import transform_error
from server.cli import main
from server.loopback import RunningServer, running_server

pytestmark = [pytest.mark.asyncio(loop_scope="module"), pytest.mark.timeout(900)]

BOARD = "charuco:15x11:40:30"
SAMPLES = 12


def _half_size_with_board(data: dict[str, Any]) -> None:
    """The lab's cameras at half resolution (a quarter of the rendering and detection), and
    the calibration board the station's hand-eye sessions look at."""
    for cam in data["cameras"]:
        w, h = cam["image_size"]
        cam["image_size"] = [w // 2, h // 2]
        i = dict(cam["intrinsics"])
        cam["intrinsics"] = {"fx": i["fx"] / 2, "fy": i["fy"] / 2,
                             "cx": (i["cx"] + 0.5) / 2 - 0.5, "cy": (i["cy"] + 0.5) / 2 - 0.5}
    data["calibration_board"] = BOARD


@dataclass
class Rehearsal:
    """The rendered set: images per camera and pose, the poses as the robot reports them."""

    root: Path
    poses: dict[str, list[float]]
    truth: dict[str, Any]

    def frames(self, sid: str) -> dict[str, np.ndarray]:
        return {cam.name: cv2.imread(str(cam / f"{sid}.png"), cv2.IMREAD_GRAYSCALE)
                for cam in sorted((self.root / "images").iterdir())}

    def error(self, calib: CalibrationFile) -> tuple[float, float]:
        """(deg, mm) of the calibration's T_gf_from_rig against the truth."""
        rig = calib.rigs[self.truth["rig"]]
        assert rig.T_gf_from_rig is not None
        return transform_error(rig.T_gf_from_rig.matrix, np.array(self.truth["T_gf_from_rig"]))


@dataclass
class Env:
    rs: RunningServer
    set: Rehearsal
    cli_error: tuple[float, float]  # mvpose calibrate handeye on the same images

    @property
    def station(self) -> Any:
        return self.rs.runtime

    async def show(self, sid: str | None) -> None:
        """The robot is at pose ``sid``: the rig's cameras see its images (None: no board)."""
        scene = self.station.scene
        view = self.station.station.views[0].id
        if sid is None:
            w, h = self.station.station.cameras[0].image_size
            frames = {c.id: np.full((h, w), 90, np.uint8) for c in self.station.station.cameras}
        else:
            frames = await asyncio.to_thread(self.set.frames, sid)
        scene.set_frames(frames, view_id=view)

    def stored(self, version: int) -> tuple[bool, CalibrationFile]:
        store = self.station.services.store
        info, content = store.versions.content("calibration", self.station.station.name, version)
        return info.active, CalibrationFile.model_validate(content)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def env(tmp_path_factory: pytest.TempPathFactory) -> AsyncIterator[Env]:
    tmp = tmp_path_factory.mktemp("handeye")
    path = station_file(tmp, "lab", relaxed_deadline, _half_size_with_board)
    root = tmp / "rehearsal"
    code = await asyncio.to_thread(main, [
        "calibrate", "synthetic", "--station", str(path), "--out", str(root), "--board", BOARD,
        "--samples", str(SAMPLES), "--robot-error", "0.05", "0.01", "--seed", "5",
        "--no-progress"])
    assert code == 0
    with (root / "poses.csv").open() as f:
        poses = {row["id"]: [float(row[k]) for k in ("X", "Y", "Z", "W", "P", "R")]
                 for row in csv.DictReader(f)}
    truth = json.loads((root / "truth.json").read_text())
    rehearsal = Rehearsal(root, poses, truth)
    out = tmp / "cli" / "handeye.json"
    code = await asyncio.to_thread(main, [
        "calibrate", "handeye", "--images", str(root / "images"), "--board", BOARD,
        "--poses", str(root / "poses.csv"), "--convention", "fanuc", "--station", str(path),
        "--out", str(out), "--no-progress"])
    assert code == 0
    cli_error = rehearsal.error(load_calibration(out))
    async with running_server(settings_for(path, tmp / "var"), runtime_options(3)) as rs:
        yield Env(rs, rehearsal, cli_error)


# --------------------------------------------------------------------------- one session
Step = Callable[..., Awaitable[tuple[int, dict[str, Any]]]]


async def run_session(env: Env, begin: Step, add: Step, calculate: Step,
                      holdout: int) -> dict[str, Any]:
    """Every refusal a robot program meets, then a whole session: the calculate's answer."""
    code, _ = await add(env.set.poses["001"])
    assert code == HandEyeCode.NO_SESSION
    code, _ = await begin(holdout)
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
    assert 0 < out["sigma_mm"] < 2.0 and out["holdout_mm"] < 1.0, out
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
