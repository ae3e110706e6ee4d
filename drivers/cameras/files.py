"""A camera that replays an image folder, for offline reprocessing: images matched to triggers
by the number in their names.

Every image's name carries a number (its last run of digits: ``0007.png``, ``frame0007.png``,
``left-7.tif``); the folder's smallest number is the first trigger's image, and trigger k takes
the image numbered ``first + k − 1`` — by name, never by position in the folder, so one missing
file fails its own trigger alone (the camera names the number it looked for) and the next
trigger still gets its own image. Each software trigger (or each grab when free running) takes
the next number, as a triggered camera exposes one frame per trigger (a frame dropped as stale
still uses its image); past the largest number the camera reports that the folder is exhausted.
Images are read as they are (:func:`read_image`): an 8-bit grey image is a frame, 8-bit colour is
converted to grey, anything else (16-bit, float) is refused with the camera, the file and the
format named.
"""

from __future__ import annotations

import re
import time
from pathlib import Path

import cv2
import numpy as np

from drivers.cameras.base import Camera, CameraSettings, Image, TriggerMode, to_mono8
from drivers.errors import DriverInitError, DriverOperationError, DriverTimeout, FrameFormatError
from mvpose_core.detect.types import image_format
from mvpose_core.station import CameraConfig

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".pgm", ".jpg", ".jpeg")


def list_images(folder: Path) -> list[Path]:
    """Image files of a folder in name order."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


_LAST_NUMBER = re.compile(r"(\d+)\D*$")


def image_number(path: Path) -> int | None:
    """The number an image's name carries (its last run of digits), None without one."""
    m = _LAST_NUMBER.search(path.stem)
    return int(m.group(1)) if m else None


def read_image(path: Path, camera_id: str) -> Image:
    """One image file as a mono8 frame: 8-bit grey as is, 8-bit colour converted to grey; an
    unreadable file or any other format is a :class:`DriverOperationError` (``FrameFormatError``)
    naming the camera, the file and the format."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise DriverOperationError(f"camera {camera_id!r} (files): cannot read {str(path)!r}")
    h, w = raw.shape[:2]
    if raw.ndim == 2 and raw.dtype == np.uint8:
        return raw  # type: ignore[return-value]  # uint8 checked above
    fmt = {3: "bgr8", 4: "bgra8"}.get(raw.shape[2] if raw.ndim == 3 else 0, "")
    if raw.dtype != np.uint8 or not fmt:
        raise FrameFormatError(
            f"camera {camera_id!r}: expected mono8, got {image_format(raw)} ({raw.dtype}) "
            f"in {path.name!r}"
        )
    return to_mono8(raw, fmt, w, h, camera_id)


class FilesCamera(Camera):
    """Replays ``driver.folder``."""

    kind = "files"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._files: dict[int, Path] = {}  # image number -> file
        self._first = 0
        self._next = 0
        self._pending: list[int] = []  # trigger indices (0 = first) not yet grabbed
        self._trigger_mode: TriggerMode = "software"
        self._roi = CameraSettings()

    def _open_device(self) -> None:
        folder = Path(self.config.driver.folder or "")
        if not folder.is_dir():
            raise DriverInitError(
                f"camera {self.camera_id!r} (files): folder {str(folder)!r} does not exist"
            )
        files = list_images(folder)
        if not files:
            raise DriverInitError(
                f"camera {self.camera_id!r} (files): no images {list(IMAGE_SUFFIXES)} "
                f"in {str(folder)!r}"
            )
        numbered: dict[int, Path] = {}
        for f in files:
            n = image_number(f)
            if n is None:
                raise DriverInitError(
                    f"camera {self.camera_id!r} (files): {f.name!r} in {str(folder)!r} has no "
                    "number in its name; images are matched to triggers by number "
                    "(e.g. 0001.png, 0002.png, ...)"
                )
            if n in numbered:
                raise DriverInitError(
                    f"camera {self.camera_id!r} (files): {numbered[n].name!r} and {f.name!r} "
                    f"in {str(folder)!r} both carry number {n}"
                )
            numbered[n] = f
        self._files = numbered
        self._first = min(numbered)
        self._next = 0

    def _configure(self, settings: CameraSettings) -> None:
        self._roi = settings  # exposure and gain mean nothing for recorded images

    def _arm(self, trigger: TriggerMode) -> None:
        if trigger == "hardware":
            raise DriverInitError(
                f"camera {self.camera_id!r} (files): no hardware trigger; use software"
            )
        self._trigger_mode = trigger
        self._pending = []

    def _disarm(self) -> None:
        self._pending = []

    def _flush(self) -> None:
        self._pending = []

    def _abort(self, armed: TriggerMode) -> None:
        self._pending = []  # nothing is in flight between calls: the queue is all there is

    def _trigger(self) -> None:
        self._pending.append(self._next)
        self._next += 1

    def _grab(self, t_end: float) -> tuple[Image, int, int | None]:
        if self._trigger_mode == "software":
            if not self._pending:
                # No trigger, no frame: wait out the deadline as a real triggered camera would.
                time.sleep(max(0.0, t_end - time.monotonic()))
                raise DriverTimeout(
                    f"camera {self.camera_id!r} (files): no trigger before the deadline"
                )
            index = self._pending.pop(0)
        else:
            index, self._next = self._next, self._next + 1
        number = self._first + index
        if number > max(self._files):
            raise DriverOperationError(
                f"camera {self.camera_id!r} (files): folder exhausted after "
                f"{len(self._files)} images"
            )
        path = self._files.get(number)
        if path is None:  # this trigger's image only; the next trigger takes the next number
            raise DriverOperationError(
                f"camera {self.camera_id!r} (files): no image numbered {number} for trigger "
                f"{index + 1} in {self.config.driver.folder!r}"
            )
        return self._crop(read_image(path, self.camera_id), path), index + 1, None

    def _crop(self, image: Image, path: Path) -> Image:
        return np.ascontiguousarray(self._full_or_region(image, f" in {path.name!r}"))

    def _close(self) -> None:
        self._files = {}
