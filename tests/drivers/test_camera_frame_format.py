"""Frames are checked, never cropped: a frame of the wrong size or format is refused naming the
camera, the expected and the actual format (issue 16; Reason.DETECTION_FAILED, operations.md)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from camera_scenes import H, W, camera_config, random_images, small_station, write_images

from drivers.cameras import SimScene, make_camera
from drivers.errors import DriverOperationError, FrameFormatError


def test_sim_camera_refuses_a_larger_frame() -> None:
    station = small_station("station1")
    scene = SimScene(station, None, np.random.default_rng(0))
    cid = station.cameras[0].id
    scene.set_frames({cid: np.zeros((2 * H, 2 * W), np.uint8)}, view_id=1)
    with make_camera(station.camera(cid), scene) as cam:
        cam.arm("software")
        cam.trigger()
        with pytest.raises(FrameFormatError) as err:
            cam.grab(1.0)
    assert str(err.value) == f"camera {cid!r}: expected {W}x{H} mono8, got {2 * W}x{2 * H} mono8"
    assert isinstance(err.value, DriverOperationError)  # the driver family, as before


def test_files_camera_refuses_a_larger_image_instead_of_cropping(tmp_path: Path) -> None:
    write_images(tmp_path / "big", random_images(np.random.default_rng(0), 1, 2 * W, 2 * H))
    with make_camera(camera_config("left1", kind="files", folder=str(tmp_path / "big"))) as cam:
        cam.arm("software")
        cam.trigger()
        with pytest.raises(FrameFormatError,
                           match=f"camera 'left1': expected {W}x{H} mono8, got {2 * W}x{2 * H} "
                                 "mono8 in 'frame0000.png'"):
            cam.grab(1.0)


def test_files_camera_refuses_colour_of_another_depth(tmp_path: Path) -> None:
    folder = tmp_path / "rgb16"
    folder.mkdir()
    cv2.imwrite(str(folder / "0001.png"), np.full((H, W, 3), 4000, dtype=np.uint16))
    with make_camera(camera_config("left1", kind="files", folder=str(folder))) as cam:
        cam.arm("software")
        cam.trigger()
        with pytest.raises(FrameFormatError,
                           match=f"camera 'left1': expected mono8, got {W}x{H} 3-channel 16-bit"):
            cam.grab(1.0)


def test_a_region_takes_the_sensor_frame_or_one_of_its_own_size(tmp_path: Path) -> None:
    images = random_images(np.random.default_rng(1), 2, W, H)
    images[1] = images[1][: H // 2, : W // 2].copy()  # recorded with the region already applied
    write_images(tmp_path / "roi", images)
    with make_camera(camera_config("c", kind="files", folder=str(tmp_path / "roi"))) as cam:
        cam.configure(width=W // 2, height=H // 2, offset_x=8, offset_y=4)
        cam.arm("software")
        cam.trigger()
        region = images[0][4 : 4 + H // 2, 8 : 8 + W // 2]
        np.testing.assert_array_equal(cam.grab(1.0).image, region)
        cam.trigger()
        np.testing.assert_array_equal(cam.grab(1.0).image, images[1])
