"""Faults each give their error within the deadline: timeout, disconnect and reconnect, corrupt or
failed frames, wrong pixel format, unknown serial (the last is in the behaviour suite)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from camera_scenes import VIKY_CTI, H, W, camera_config, random_images, small_station, write_images

from drivers.cameras import (
    Backoff,
    Camera,
    CaptureGroup,
    DeviceLostError,
    DriverInitError,
    DriverOperationError,
    DriverTimeout,
    SimScene,
    backend_class,
    make_camera,
)

SLACK_S = 0.5  # what a loaded machine may add to a deadline; tells "at the deadline" from "hung"


@pytest.fixture(scope="module")
def scene() -> SimScene:
    station = small_station("station1")
    s = SimScene(station, None, np.random.default_rng(2))
    s.set_part_pose(station.recipe().T_rf_from_pf0.matrix)
    return s


def sim_camera(scene: SimScene, camera_id: str, **driver: Any) -> Camera:
    cfg = scene.station.camera(camera_id)
    if "fault" in driver:
        driver["fault"] = cfg.driver.fault.model_copy(update=driver["fault"])
    return make_camera(
        cfg.model_copy(update={"driver": cfg.driver.model_copy(update=driver)}), scene
    )


def poll(condition: Any, timeout_s: float) -> bool:
    """Wait for ``condition()`` to hold, checking often, at most ``timeout_s``."""
    t_end = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > t_end:
            return False
        time.sleep(0.01)
    return True


# ---------------------------------------------------------------------------- timeout


def test_sim_timeout_fault_every_second_grab(scene: SimScene) -> None:
    cid = scene.station.cameras[0].id
    with sim_camera(scene, cid, fault={"kind": "timeout", "every_n": 2}) as cam:
        cam.arm("software")
        cam.trigger()
        assert cam.grab(1.0).frame_id == 1
        cam.trigger()
        t0 = time.monotonic()
        with pytest.raises(DriverTimeout, match="simulated timeout"):
            cam.grab(0.2)
        assert 0.19 <= time.monotonic() - t0 < 0.2 + SLACK_S
        cam.trigger()
        assert cam.grab(1.0).frame_id == 2


def test_sim_latency_beyond_the_deadline_times_out_at_the_deadline(scene: SimScene) -> None:
    with sim_camera(scene, scene.station.cameras[0].id, latency_ms=5000.0) as cam:
        cam.arm("software")
        cam.trigger()
        t0 = time.monotonic()
        with pytest.raises(DriverTimeout):
            cam.grab(0.1)
        assert time.monotonic() - t0 < 0.1 + SLACK_S


def test_viky_timeout_when_the_next_frame_is_later_than_the_deadline() -> None:
    cfg = camera_config(
        "viky", kind="genicam", serial="2", cti=VIKY_CTI, features={"AcquisitionFrameRate": 1.0}
    )
    with make_camera(cfg) as cam:
        cam.arm("free_run")
        cam.grab(3.0)
        t0 = time.monotonic()
        with pytest.raises(DriverTimeout, match="no frame before the deadline"):
            cam.grab(0.1)  # the next frame is about a second away
        assert 0.09 <= time.monotonic() - t0 < 0.1 + SLACK_S


# ---------------------------------------------------------------------------- disconnect


def test_sim_disconnect_mid_acquisition_then_reconnect(scene: SimScene) -> None:
    ids = [c.id for c in scene.station.cameras]
    flaky = sim_camera(scene, ids[0], fault={"kind": "disconnect", "every_n": 2, "down_ms": 300.0})
    others = [sim_camera(scene, cid) for cid in ids[1:]]
    with CaptureGroup(
        [flaky, *others], backoff=Backoff(first_s=0.05, factor=2.0, max_s=0.2)
    ) as group:
        assert all(e is None for e in group.wait_ready(5.0).values())
        assert all(f.image.shape == (H, W) for f in group.grab_all(1.0).values())  # type: ignore[union-attr]

        t0 = time.monotonic()
        lost = group.grab_all(1.0)  # the second grab of the flaky camera loses the device
        assert time.monotonic() - t0 < 1.0 + SLACK_S
        assert isinstance(lost[ids[0]], DeviceLostError)
        assert all(not isinstance(lost[cid], Exception) for cid in ids[1:])

        during = group.grab_all(1.0)  # answered at once while the worker reconnects
        assert isinstance(during[ids[0]], DeviceLostError) and "reconnecting" in str(during[ids[0]])
        assert all(not isinstance(during[cid], Exception) for cid in ids[1:])

        assert poll(lambda: group.status()[ids[0]].startswith("up"), 5.0), group.status()
        assert group.status()[ids[0]] == "up (1 reconnects)"
        back = group.grab_all(1.0)
        assert all(not isinstance(r, Exception) for r in back.values()), back


def test_sim_camera_cannot_be_opened_while_down(scene: SimScene) -> None:
    cid = scene.station.cameras[0].id
    cam = sim_camera(scene, cid, fault={"kind": "disconnect", "every_n": 1, "down_ms": 200.0})
    cam.open()
    cam.arm("software")
    cam.trigger()
    with pytest.raises(DeviceLostError, match="device lost"):
        cam.grab(1.0)
    cam.close()
    with pytest.raises(DriverInitError, match="not reachable"):
        cam.open()
    assert poll(lambda: _opens(cam), 3.0)
    cam.close()


def _opens(cam: Camera) -> bool:
    try:
        cam.open()
    except DriverInitError:
        return False
    return True


# ---------------------------------------------------------------------------- bad frames


def test_sim_corrupt_frame_is_an_operation_error(scene: SimScene) -> None:
    with sim_camera(
        scene, scene.station.cameras[1].id, fault={"kind": "corrupt", "every_n": 2}
    ) as cam:
        cam.arm("software")
        for expect_error in (False, True, False):
            cam.trigger()
            if expect_error:
                with pytest.raises(DriverOperationError, match="incomplete"):
                    cam.grab(1.0)
            else:
                cam.grab(1.0)


def test_pylon_failed_buffer_is_an_operation_error() -> None:
    with make_camera(camera_config("basler", kind="pylon", serial="0815-0001")) as cam:
        cam.arm("software")
        node = cam.instant_camera  # type: ignore[attr-defined]
        node.ForceFailedBufferCount.Value = 1
        node.ForceFailedBuffer.Execute()  # the emulator's "this transfer failed"
        cam.trigger()
        with pytest.raises(DriverOperationError, match="failed"):
            cam.grab(1.0)
        cam.trigger()
        assert cam.grab(1.0).image.shape == (H, W)


# ---------------------------------------------------------------------------- pixel format


def test_files_16_bit_image_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "deep"
    folder.mkdir()
    cv2.imwrite(str(folder / "0001.png"), np.full((H, W), 4000, dtype=np.uint16))
    with make_camera(camera_config("deep", kind="files", folder=str(folder))) as cam:
        cam.arm("software")
        cam.trigger()
        with pytest.raises(
            DriverOperationError, match=f"camera 'deep': expected mono8, got {W}x{H} mono16"
        ):
            cam.grab(1.0)


def test_files_wrong_size_is_refused(tmp_path: Path) -> None:
    write_images(tmp_path / "big", random_images(np.random.default_rng(0), 1, W // 2, H // 2))
    with make_camera(camera_config("small", kind="files", folder=str(tmp_path / "big"))) as cam:
        cam.arm("software")
        cam.trigger()
        with pytest.raises(DriverOperationError, match=f"expected {W}x{H} mono8"):
            cam.grab(1.0)


def test_pylon_device_switched_to_mono12_is_refused() -> None:
    with make_camera(camera_config("basler", kind="pylon", serial="0815-0002")) as cam:
        cam.configure()
        cam.instant_camera.PixelFormat.Value = "Mono12"  # type: ignore[attr-defined]  # as from pylon Viewer
        cam.arm("software")
        cam.trigger()
        with pytest.raises(DriverOperationError, match=f"got {W}x{H} Mono12"):
            cam.grab(1.0)


def test_viky_pixel_format_it_does_not_offer() -> None:
    with make_camera(camera_config("viky", kind="genicam", serial="0", cti=VIKY_CTI)) as cam:
        with pytest.raises(
            DriverInitError,
            match="PixelFormat 'bgr8' not offered; device has \\['RGBa8', 'Mono8'\\]",
        ):
            cam.configure(pixel_format="bgr8")
        with pytest.raises(DriverInitError, match="Width = 5000 outside"):
            cam.configure(width=5000)


# ---------------------------------------------------------------------------- backend table


def test_backend_table_errors(scene: SimScene) -> None:
    with pytest.raises(DriverInitError, match="unknown camera driver kind 'gige'"):
        backend_class("gige")
    with pytest.raises(DriverInitError, match="needs a SimScene"):
        make_camera(scene.station.cameras[0])
    with pytest.raises(DriverInitError, match="driver.cti"):
        make_camera(camera_config("g", kind="genicam", serial="0")).open()


def test_backends_are_imported_only_when_used() -> None:
    code = (
        "import sys, drivers.cameras as c; c.backend_class('files'); "
        "heavy = ('pypylon', 'harvesters', 'mvpose_core.render'); "
        "print(sorted(m for m in heavy if m in sys.modules))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=Path(__file__).resolve().parents[2],
        check=True,
    )
    assert out.stdout.strip() == "[]"
