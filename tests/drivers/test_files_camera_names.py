"""The files camera matches images to triggers by the number in their names, never by order."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from camera_scenes import H, W, camera_config

from drivers.cameras import make_camera
from drivers.errors import DriverInitError, DriverOperationError


def _write(folder: Path, names: list[str]) -> dict[str, np.ndarray]:
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for k, name in enumerate(names):
        img = np.full((H, W), 10 + 20 * k, dtype=np.uint8)
        assert cv2.imwrite(str(folder / name), img)
        out[name] = img
    return out


def test_a_missing_image_fails_its_own_trigger_only(tmp_path: Path) -> None:
    images = _write(tmp_path / "run", ["part-0007.png", "part-0008.png", "part-0010.png"])
    with make_camera(camera_config("cam", kind="files", folder=str(tmp_path / "run"))) as cam:
        cam.arm("software")
        cam.trigger()
        assert np.array_equal(cam.grab(1.0).image, images["part-0007.png"])
        cam.trigger()
        assert np.array_equal(cam.grab(1.0).image, images["part-0008.png"])
        cam.trigger()
        with pytest.raises(DriverOperationError, match="no image numbered 9 for trigger 3"):
            cam.grab(1.0)
        cam.trigger()  # the next trigger still gets its own image, not a shifted one
        assert np.array_equal(cam.grab(1.0).image, images["part-0010.png"])
        cam.trigger()
        with pytest.raises(DriverOperationError, match="exhausted after 3 images"):
            cam.grab(1.0)


@pytest.mark.parametrize(("names", "words"), [
    (["0001.png", "left.png"], "'left.png' .* has no number in its name"),
    (["0001.png", "frame1.png"], "'0001.png' and 'frame1.png' .* both carry number 1"),
])
def test_names_without_a_number_or_twice_the_same_are_refused(
    tmp_path: Path, names: list[str], words: str
) -> None:
    _write(tmp_path / "bad", names)
    cam = make_camera(camera_config("cam", kind="files", folder=str(tmp_path / "bad")))
    with pytest.raises(DriverInitError, match=words):
        cam.open()
    cam.close()
