"""CaptureGroup: every camera in parallel, one deadline, one camera's failure stays its own."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from camera_scenes import VIKY_CTI, H, W, camera_config, small_station

from drivers.cameras import (
    Backoff,
    Camera,
    CameraSettings,
    CaptureGroup,
    DeviceLostError,
    DriverInitError,
    DriverOperationError,
    DriverTimeout,
    Frame,
    SimScene,
    capture_station,
    make_camera,
)
from drivers.cameras.base import Image, TriggerMode
from drivers.cameras.capture import PreviewPreemptedError

SLACK_S = 0.5  # what a loaded machine may add to a deadline; tells "at the deadline" from "hung"


class StuckCamera(Camera):
    """A device whose vendor call ignores every timeout until released (a test backend)."""

    kind = "stuck"

    def __init__(self, camera_id: str) -> None:
        super().__init__(camera_config(camera_id, kind="files", folder="/nonexistent"))
        self.release = threading.Event()

    def _open_device(self) -> None:
        pass

    def _configure(self, settings: CameraSettings) -> None:
        pass

    def _arm(self, trigger: TriggerMode) -> None:
        pass

    def _disarm(self) -> None:
        pass

    def _trigger(self) -> None:
        pass

    def _grab(self, t_end: float) -> tuple[Image, int, int | None]:
        self.release.wait()
        return np.zeros((H, W), np.uint8), 1, None

    def _close(self) -> None:
        pass


@pytest.fixture(scope="module")
def scene() -> SimScene:
    station = small_station("station1")
    s = SimScene(station, None, np.random.default_rng(3))
    s.set_part_pose(station.recipe().T_rf_from_pf0.matrix)
    return s


def sim_cameras(scene: SimScene, **driver: Any) -> list[Camera]:
    out = []
    for cfg in scene.station.cameras:
        out.append(
            make_camera(
                cfg.model_copy(update={"driver": cfg.driver.model_copy(update=driver)}), scene
            )
        )
    return out


def test_all_cameras_of_a_fixed_station_in_one_call(scene: SimScene) -> None:
    with CaptureGroup(sim_cameras(scene, latency_ms=30.0)) as group:
        assert all(e is None for e in group.wait_ready(5.0).values())
        t0 = time.monotonic()
        frames = group.grab_all(1.0)
        elapsed = time.monotonic() - t0
        assert list(frames) == [c.id for c in scene.station.cameras]
        for cid, f in frames.items():
            assert isinstance(f, Frame) and f.camera_id == cid
            np.testing.assert_array_equal(f.image, scene.truth(cid).image)
        # 4 cameras x 30 ms latency in parallel: well under the 120 ms a serial grab would take.
        assert elapsed < 4 * 0.030 + SLACK_S
        starts = [f.t_trigger for f in frames.values()]  # type: ignore[union-attr]
        assert max(starts) - min(starts) < 0.03 + SLACK_S


def test_a_grab_for_a_view_shows_the_simulated_cameras_that_view() -> None:
    station = small_station("lab")
    scene = SimScene(station, None, np.random.default_rng(4))
    scene.set_part_pose(station.recipe().T_rf_from_pf0.matrix)
    assert scene.view == 1
    with CaptureGroup(sim_cameras(scene)) as group:
        assert all(e is None for e in group.wait_ready(5.0).values())
        for view in (2, 1, 2):
            frames = group.grab_all(1.0, view=view)
            assert scene.view == view
            for cid, f in frames.items():
                assert isinstance(f, Frame)
                np.testing.assert_array_equal(f.image, scene.truth(cid, view).image)
                other = 3 - view
                assert not np.array_equal(f.image, scene.truth(cid, other).image)


def test_a_preview_gives_each_cameras_frame_between_triggers(scene: SimScene) -> None:
    with CaptureGroup(sim_cameras(scene, latency_ms=10.0)) as group:
        assert all(e is None for e in group.wait_ready(5.0).values())
        frames = group.preview(2.0)
        assert list(frames) == [c.id for c in scene.station.cameras]
        for cid, f in frames.items():
            assert isinstance(f, Frame), f
            np.testing.assert_array_equal(f.image, scene.truth(cid).image)
        # the preview left nothing behind: the next trigger's frames are the trigger's own
        t = time.monotonic()
        for f in group.grab_all(2.0).values():
            assert isinstance(f, Frame) and f.t_trigger >= t


def test_a_trigger_preempts_a_preview_and_gets_its_own_frame(scene: SimScene) -> None:
    """The preview's exposure is in flight when the trigger comes: the preview gives way, its
    exposure is dropped, and the trigger's frame is exposed after the trigger (never the
    preview's frame handed over as the trigger's)."""
    latency_s = 0.3
    cams = sim_cameras(scene, latency_ms=latency_s * 1000)
    with CaptureGroup(cams) as group:
        assert all(e is None for e in group.wait_ready(5.0).values())
        out: dict[str, Any] = {}
        previewer = threading.Thread(target=lambda: out.update(group.preview(10.0)))
        previewer.start()
        # every camera has had its preview trigger (the simulated exposure is now in flight)
        assert _poll(lambda: all(c._pending for c in cams), 5.0)  # type: ignore[attr-defined]
        t = time.monotonic()
        frames = group.grab_all(5.0)
        previewer.join(10.0)
        assert not previewer.is_alive()
        for cam in cams:
            f = frames[cam.camera_id]
            assert isinstance(f, Frame), f
            assert f.t_trigger >= t  # its own trigger ...
            assert f.t_received >= f.t_trigger + latency_s  # ... and its own exposure
            assert isinstance(out[cam.camera_id], PreviewPreemptedError)
        # nothing of the dropped preview is left to be taken for a later frame
        late = group.grab_all(0.05, trigger=False)
        assert all(isinstance(r, DriverTimeout) for r in late.values())


def test_a_preview_stays_out_of_a_running_trigger(scene: SimScene) -> None:
    cams = sim_cameras(scene, latency_ms=300.0)
    with CaptureGroup(cams) as group:
        assert all(e is None for e in group.wait_ready(5.0).values())
        out: dict[str, Any] = {}
        trig = threading.Thread(target=lambda: out.update(group.grab_all(5.0)))
        trig.start()
        assert _poll(lambda: all(c._pending for c in cams), 5.0)  # type: ignore[attr-defined]
        busy = group.preview(1.0)
        trig.join(10.0)
        assert all(isinstance(r, PreviewPreemptedError) for r in busy.values())
        assert all(isinstance(f, Frame) for f in out.values())


def test_slow_camera_times_out_alone(scene: SimScene) -> None:
    cams = sim_cameras(scene)
    slow_cfg = cams[0].config.model_copy(
        update={"driver": cams[0].config.driver.model_copy(update={"latency_ms": 3000.0})}
    )
    cams[0] = make_camera(slow_cfg, scene)
    with CaptureGroup(cams) as group:
        group.wait_ready(5.0)
        t0 = time.monotonic()
        res = group.grab_all(0.2)
        assert time.monotonic() - t0 < 0.2 + SLACK_S
        assert isinstance(res[cams[0].camera_id], DriverTimeout)
        assert all(isinstance(res[c.camera_id], Frame) for c in cams[1:])


def test_hung_vendor_call_never_hangs_the_group(scene: SimScene) -> None:
    stuck = StuckCamera("stuck")
    with CaptureGroup([stuck, *sim_cameras(scene)]) as group:
        group.wait_ready(5.0)
        t0 = time.monotonic()
        first = group.grab_all(0.1)
        assert time.monotonic() - t0 < 0.1 + SLACK_S
        assert isinstance(first["stuck"], DriverTimeout)
        second = group.grab_all(0.1)  # still inside the vendor call: refused at once
        assert isinstance(second["stuck"], DriverOperationError) and "still busy" in str(
            second["stuck"]
        )
        assert sum(isinstance(r, Frame) for r in second.values()) == len(scene.station.cameras)
        stuck.release.set()  # the device answers at last; the worker is free again
        assert _poll(lambda: isinstance(group.grab_all(0.5)["stuck"], Frame), 5.0)


def test_camera_that_never_opens_is_retried_with_backoff(scene: SimScene) -> None:
    ghost_cfg = scene.station.cameras[0].model_copy(
        update={
            "id": "ghost",
            "driver": scene.station.cameras[0].driver.model_copy(update={"serial": "SIM-GONE"}),
        }
    )
    ghost = make_camera(ghost_cfg, scene)
    with CaptureGroup([ghost, *sim_cameras(scene)], backoff=Backoff(0.02, 2.0, 0.1)) as group:
        ready = group.wait_ready(2.0)
        assert isinstance(ready["ghost"], DriverInitError) and "SIM-GONE" in str(ready["ghost"])
        res = group.grab_all(0.5)
        assert isinstance(res["ghost"], DeviceLostError) and "reconnecting" in str(res["ghost"])
        assert sum(isinstance(r, Frame) for r in res.values()) == len(scene.station.cameras)
        assert group.status()["ghost"].startswith("down:")


def test_three_viky_devices_share_one_producer() -> None:
    cams = [
        make_camera(camera_config(f"viky{s}", kind="genicam", serial=s, cti=VIKY_CTI))
        for s in "012"
    ]
    with CaptureGroup(cams) as group:
        assert all(e is None for e in group.wait_ready(10.0).values()), group.status()
        for _ in range(2):
            res = group.grab_all(2.0)
            assert all(isinstance(f, Frame) and f.image.shape == (H, W) for f in res.values()), res


def test_hardware_trigger_of_the_sim(scene: SimScene) -> None:
    with CaptureGroup(sim_cameras(scene), trigger="hardware") as group:
        group.wait_ready(5.0)
        quiet = group.grab_all(0.1)
        assert all(isinstance(r, DriverTimeout) for r in quiet.values())
        t = threading.Timer(0.05, scene.hardware_trigger)  # the PLC's pulse, from another thread
        t.start()
        try:
            res = group.grab_all(2.0)
        finally:
            t.join()
        assert all(isinstance(f, Frame) and np.isnan(f.t_trigger) for f in res.values())


def test_capture_station_and_a_subset_of_cameras(scene: SimScene) -> None:
    with capture_station(scene.station, scene) as group:
        assert group.camera_ids == [c.id for c in scene.station.cameras]
        group.wait_ready(5.0)
        some = group.camera_ids[1:3]
        res = group.grab_all(1.0, camera_ids=some)
        assert list(res) == some and all(isinstance(f, Frame) for f in res.values())
        with pytest.raises(ValueError, match="no cameras \\['nope'\\]"):
            group.grab_all(1.0, camera_ids=["nope"])


def test_pylon_hardware_trigger_line_from_features() -> None:
    cfg = camera_config(
        "basler", kind="pylon", serial="0815-0001", features={"TriggerSource": "Line2"}
    )
    with make_camera(cfg) as cam:
        cam.arm("hardware")
        assert cam.instant_camera.TriggerSource.Value == "Line2"  # type: ignore[attr-defined]
        with pytest.raises(DriverTimeout):
            cam.grab(0.1)  # nobody pulses the line


def test_backoff_delays() -> None:
    b = Backoff(first_s=0.1, factor=2.0, max_s=0.5)
    assert [b.delay(k) for k in range(5)] == pytest.approx([0.1, 0.2, 0.4, 0.5, 0.5])
    with pytest.raises(ValueError, match="factor >= 1"):
        Backoff(first_s=0.1, factor=0.5)


def test_group_rejects_duplicate_ids_and_use_after_close(scene: SimScene) -> None:
    cams = sim_cameras(scene)
    with pytest.raises(ValueError, match="unique ids"):
        CaptureGroup([cams[0], cams[0]])
    group = CaptureGroup(cams[:1])
    group.close()
    with pytest.raises(DriverOperationError, match="closed"):
        group.grab_all(0.1)
    assert not cams[0].is_open


def _poll(condition: Any, timeout_s: float) -> bool:
    t_end = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > t_end:
            return False
    return True


def test_docs_example_runs() -> None:
    """The first Python block of docs/cameras.md is executable as written."""
    root = Path(__file__).resolve().parents[2]
    text = (root / "docs" / "cameras.md").read_text()
    code = text.split("```python\n", 1)[1].split("```", 1)[0]
    cwd = os.getcwd()
    os.chdir(root)  # the example names the station file relative to the repository
    try:
        exec(compile(code, "docs/cameras.md", "exec"), {})
    finally:
        os.chdir(cwd)
