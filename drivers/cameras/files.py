"""A camera that replays an image folder in name order, for offline reprocessing.

Each software trigger (or each grab when free running) takes the next image, as a triggered
camera exposes one frame per trigger (so a frame dropped as stale still uses its image); after the
last one the camera reports that the folder is exhausted. Images are read as they are: an 8-bit grey
image is a frame, 8-bit colour is converted to grey, anything else (16-bit, float) is refused
with the camera, the file and the format named.
"""

from __future__ import annotations

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


class FilesCamera(Camera):
    """Replays ``driver.folder``."""

    kind = "files"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._files: list[Path] = []
        self._next = 0
        self._pending: list[int] = []  # file indices taken by triggers, not yet grabbed
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
        self._files = files
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
        if index >= len(self._files):
            raise DriverOperationError(
                f"camera {self.camera_id!r} (files): folder exhausted after "
                f"{len(self._files)} images"
            )
        path = self._files[index]
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise DriverOperationError(
                f"camera {self.camera_id!r} (files): cannot read {str(path)!r}"
            )
        image = self._to_mono(raw, path)
        return self._crop(image, path), index + 1, None

    def _to_mono(self, raw: np.ndarray, path: Path) -> Image:
        h, w = raw.shape[:2]
        if raw.ndim == 2 and raw.dtype == np.uint8:
            return raw
        fmt = {3: "bgr8", 4: "bgra8"}.get(raw.shape[2] if raw.ndim == 3 else 0, "")
        if raw.dtype != np.uint8 or not fmt:
            raise FrameFormatError(
                f"camera {self.camera_id!r}: expected mono8, got {image_format(raw)} ({raw.dtype}) "
                f"in {path.name!r}"
            )
        return to_mono8(raw, fmt, w, h, self.camera_id)

    def _crop(self, image: Image, path: Path) -> Image:
        return np.ascontiguousarray(self._full_or_region(image, f" in {path.name!r}"))

    def _close(self) -> None:
        self._files = []
