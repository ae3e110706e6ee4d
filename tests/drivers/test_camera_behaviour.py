"""One behaviour suite for every camera backend (python-can's back-to-back pattern).

:class:`CameraBehaviour` holds the tests; each ``Test<Backend>`` subclass supplies a factory for
fresh cameras of its backend and, where the backend can know it, the images consecutive triggers
must show. All of them always run: the sim and files backends need nothing, pylon's camera
emulation and the viky.cti GenTL producer come from PyPI (pypylon, genicam).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from camera_scenes import VIKY_CTI, H, W, camera_config, random_images, small_station, write_images

from drivers.cameras import (
    Camera,
    DriverInitError,
    DriverOperationError,
    DriverTimeout,
    SimScene,
    make_camera,
)

Factory = Callable[..., Camera]
# What a loaded 2-core machine may add on top of a deadline. Not a speed target: it only tells
# "returned at the deadline" from "hung".
SLACK_S = 0.5


class CameraBehaviour:
    """The contract of :class:`drivers.cameras.Camera`; subclasses provide the fixtures below."""

    @pytest.fixture
    def make(self) -> Factory:
        """Factory of fresh, closed cameras; keyword arguments override driver fields."""
        raise NotImplementedError

    @pytest.fixture
    def expected(self) -> list[np.ndarray] | None:
        """Images that consecutive triggers after arm() show (cycling), or None if unknowable."""
        return None

    @pytest.fixture
    def missing(self, make: Factory) -> tuple[Camera, str]:
        """A camera whose device does not exist, and a text its error must contain."""
        return make(serial="NOPE-0000"), "NOPE-0000"

    def settle(self, cam: Camera) -> None:
        """Wait until a triggered, not yet grabbed frame has reached the driver."""

    @pytest.fixture
    def cam(self, make: Factory) -> Iterator[Camera]:
        c = make()
        c.open()
        yield c
        c.close()

    # ------------------------------------------------------------------ tests
    def test_software_triggers_give_their_frames(
        self, cam: Camera, expected: list[np.ndarray] | None
    ) -> None:
        cam.configure()
        cam.arm("software")
        ids = []
        for k in range(3):
            t = cam.trigger()
            f = cam.grab(2.0)
            assert f.camera_id == cam.camera_id
            assert f.image.dtype == np.uint8 and f.image.shape == (H, W)
            assert f.t_trigger == t <= f.t_received
            assert f.image.min() < f.image.max()  # an image, not a blank buffer
            if expected is not None:
                np.testing.assert_array_equal(f.image, expected[k % len(expected)])
            ids.append(f.frame_id)
        assert ids == sorted(set(ids))

    def test_no_trigger_times_out_at_the_deadline(self, cam: Camera) -> None:
        cam.arm("software")
        t0 = time.monotonic()
        with pytest.raises(DriverTimeout, match=cam.camera_id) as info:
            cam.grab(0.15)
        elapsed = time.monotonic() - t0
        assert isinstance(info.value, TimeoutError)
        assert 0.14 <= elapsed < 0.15 + SLACK_S
        cam.trigger()  # the camera still works after a timeout
        assert cam.grab(2.0).image.shape == (H, W)

    def test_stale_frame_is_dropped_before_a_trigger(
        self, cam: Camera, expected: list[np.ndarray] | None
    ) -> None:
        cam.arm("software")
        cam.trigger()
        self.settle(cam)  # the first frame now waits in the driver, never grabbed
        t = cam.trigger()
        f = cam.grab(2.0)
        assert f.t_trigger == t
        if expected is not None:
            np.testing.assert_array_equal(f.image, expected[1 % len(expected)])

    def test_abort_drops_the_frame_in_flight(self, cam: Camera) -> None:
        cam.arm("software")
        cam.trigger()
        self.settle(cam)
        cam.abort()  # the live view's preview gives way to a trigger
        with pytest.raises(DriverTimeout):
            cam.grab(0.2)
        t = cam.trigger()
        f = cam.grab(2.0)
        assert f.t_trigger == t and f.image.shape == (H, W)

    def test_free_run(self, cam: Camera) -> None:
        cam.arm("free_run")
        a, b = cam.grab(2.0), cam.grab(2.0)
        assert b.frame_id > a.frame_id and np.isnan(a.t_trigger)
        with pytest.raises(DriverOperationError, match="arm\\('software'\\)"):
            cam.trigger()

    def test_calls_out_of_order_are_errors(self, make: Factory) -> None:
        c = make()
        with pytest.raises(DriverOperationError, match="closed"):
            c.grab(0.1)
        c.open()
        try:
            with pytest.raises(DriverOperationError, match="before arm"):
                c.grab(0.1)
            with pytest.raises(DriverOperationError, match="needs arm"):
                c.trigger()
            c.arm("software")
            with pytest.raises(DriverOperationError, match="while armed"):
                c.configure(width=W // 2)
        finally:
            c.close()
        c.close()  # twice is fine

    def test_start_stop_cycles(self, cam: Camera) -> None:
        for _ in range(4):
            cam.arm("software")
            cam.disarm()  # stop right after start
        cam.arm("software")
        cam.trigger()
        assert cam.grab(2.0).image.shape == (H, W)

    def test_reopen_after_close(self, cam: Camera) -> None:
        cam.arm("software")
        cam.trigger()
        first = cam.grab(2.0)
        cam.close()
        assert not cam.is_open and cam.armed is None
        cam.open()
        cam.arm("software")
        cam.trigger()
        again = cam.grab(2.0)
        assert again.image.shape == first.image.shape == (H, W)
        cam.reopen()  # close + open + configure + arm in one call
        assert cam.armed == "software"
        cam.trigger()
        assert cam.grab(2.0).image.shape == (H, W)

    def test_region_of_interest(self, cam: Camera, expected: list[np.ndarray] | None) -> None:
        cam.configure(width=W // 2, height=H // 2)
        cam.arm("software")
        cam.trigger()
        f = cam.grab(2.0)
        assert f.image.shape == (H // 2, W // 2)
        if expected is not None:
            np.testing.assert_array_equal(f.image, expected[0][: H // 2, : W // 2])

    def test_unsupported_pixel_format(self, cam: Camera) -> None:
        with pytest.raises(DriverInitError, match="'mono12'"):
            cam.configure(pixel_format="mono12")
        with pytest.raises(DriverInitError, match="unknown settings \\['shutter'\\]"):
            cam.configure(shutter=3)

    def test_unknown_device_is_an_init_error(self, missing: tuple[Camera, str]) -> None:
        c, text = missing
        t0 = time.monotonic()
        with pytest.raises(DriverInitError, match=text):
            c.open()
        assert time.monotonic() - t0 < 2.0 + SLACK_S
        assert not c.is_open


# ---------------------------------------------------------------------------- backends


@pytest.fixture(scope="module")
def scene() -> SimScene:
    station = small_station("lab")
    s = SimScene(station, None, np.random.default_rng(6))
    s.set_part_pose(station.recipe().T_rf_from_pf0.matrix)
    return s


@pytest.fixture(scope="module")
def rendered_station_images(scene: SimScene) -> list[np.ndarray]:
    """Every camera of every view of the lab station, rendered: what pylon is fed."""
    return [scene.truth(cid, view).image for view in (1, 2) for cid in ("left", "right")]


class TestSimCamera(CameraBehaviour):
    @pytest.fixture
    def make(self, scene: SimScene) -> Factory:
        def factory(**driver: Any) -> Camera:
            cfg = scene.station.camera("left")
            cfg = cfg.model_copy(update={"driver": cfg.driver.model_copy(update=driver)})
            return make_camera(cfg, scene)

        return factory

    @pytest.fixture
    def expected(self, scene: SimScene) -> list[np.ndarray]:
        return [scene.truth("left").image]


class TestFilesCamera(CameraBehaviour):
    @pytest.fixture
    def images(self) -> list[np.ndarray]:
        return random_images(np.random.default_rng(1), 8)

    @pytest.fixture
    def make(self, tmp_path: Path, images: list[np.ndarray]) -> Factory:
        folder = tmp_path / "replay"
        write_images(folder, images)

        def factory(**driver: Any) -> Camera:
            return make_camera(
                camera_config("replay", **{"kind": "files", "folder": str(folder), **driver})
            )

        return factory

    @pytest.fixture
    def expected(self, images: list[np.ndarray]) -> list[np.ndarray]:
        return images

    @pytest.fixture
    def missing(self, tmp_path: Path) -> tuple[Camera, str]:
        gone = tmp_path / "no-such-folder"
        return make_camera(
            camera_config("replay", kind="files", folder=str(gone))
        ), "does not exist"

    def test_folder_runs_out(self, make: Factory, images: list[np.ndarray]) -> None:
        with make() as c:
            c.arm("free_run")
            for _ in images:
                c.grab(1.0)
            with pytest.raises(DriverOperationError, match="exhausted after 8 images"):
                c.grab(1.0)


class TestPylonCamera(CameraBehaviour):
    """pylon camera emulation (PYLON_CAMEMU, set by conftest) fed the station's rendered images."""

    @pytest.fixture
    def make(self, tmp_path: Path, rendered_station_images: list[np.ndarray]) -> Factory:
        folder = tmp_path / "emulation"
        write_images(folder, rendered_station_images)
        features = {"ImageFilename": str(folder), "ImageFileMode": "On", "TestImageSelector": "Off"}

        def factory(**driver: Any) -> Camera:
            fields = {"kind": "pylon", "serial": "0815-0000", "features": features, **driver}
            return make_camera(camera_config("basler", **fields))

        return factory

    @pytest.fixture
    def expected(self, rendered_station_images: list[np.ndarray]) -> list[np.ndarray]:
        return rendered_station_images

    def settle(self, cam: Camera) -> None:
        # pylon's own wait object: signalled once a result is queued (waits for a condition).
        assert cam.instant_camera.GetGrabResultWaitObject().Wait(2000)  # type: ignore[attr-defined]


class TestGenICamCamera(CameraBehaviour):
    """harvesters on the viky.cti producer (free running; software trigger emulated)."""

    @pytest.fixture
    def make(self) -> Factory:
        def factory(**driver: Any) -> Camera:
            fields = {"kind": "genicam", "serial": "1", "cti": VIKY_CTI, **driver}
            return make_camera(camera_config("viky", **fields))

        return factory

    def test_color_device_frames_become_mono(self, cam: Camera) -> None:
        cam.configure(pixel_format="rgba8")  # viky's own default format
        cam.arm("software")
        cam.trigger()
        f = cam.grab(2.0)
        assert f.image.shape == (H, W) and f.image.dtype == np.uint8
        assert cam.trigger_emulated  # type: ignore[attr-defined]
