"""The one camera interface every backend implements, and the frame it returns.

The public methods live here and do the bookkeeping every backend needs the same way (state
checks, a lock, wrapping stray vendor exceptions, checking the delivered image); a backend only
fills in the ``_hooks``, as python-can's ``BusABC`` does. A camera's life::

    cam = open_camera(config)          # not yet connected
    cam.open()                         # find the device by serial or user id
    cam.configure()                    # exposure, gain, region, pixel format (config by default)
    cam.arm("software")                # start acquisition, waiting for triggers
    t = cam.trigger()                  # software trigger (not for hardware / free_run)
    frame = cam.grab(0.2)              # the frame of that trigger, or DriverTimeout after 0.2 s
    cam.close()

Times are ``time.monotonic()`` seconds. ``grab(deadline_s)`` takes a duration; it never blocks
longer than that (plus the time one vendor call takes to return, which the backends keep short).
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import ClassVar, Literal, TypeVar

import cv2
import numpy as np
from numpy.typing import NDArray

from drivers.errors import (
    DeviceLostError,
    DriverError,
    DriverInitError,
    DriverOperationError,
    FrameFormatError,
)
from mvpose_core.detect.types import image_format
from mvpose_core.station import CameraConfig

T = TypeVar("T")
TriggerMode = Literal["software", "hardware", "free_run"]
TRIGGER_MODES: tuple[str, ...] = ("software", "hardware", "free_run")
Image = NDArray[np.uint8]
# Device pixel formats a frame can be made from (lower case, without "Packed"): mono8 as is,
# 8-bit colour converted to grey (the viky.cti devices start in RGBa8).
PIXEL_FORMATS: tuple[str, ...] = ("mono8", "rgba8", "bgra8", "rgb8", "bgr8")


@dataclass(frozen=True)
class Frame:
    """One image from one camera, with where it came from and when."""

    camera_id: str
    image: Image  # ["H", "W"] uint8 mono
    frame_id: int  # counter of the device or driver; grows by one per delivered frame
    t_trigger: float  # monotonic s the software trigger was sent; nan when not software-triggered
    t_received: float  # monotonic s the driver held the image in memory
    device_timestamp_ns: int | None = None  # the camera's own clock, when it reports one


@dataclass(frozen=True)
class CameraSettings:
    """What :meth:`Camera.configure` sets; ``None`` leaves the device's value alone."""

    exposure_us: float | None = None
    gain_db: float | None = None
    width: int | None = None
    height: int | None = None
    offset_x: int = 0
    offset_y: int = 0
    pixel_format: str = "mono8"  # the device's format, one of PIXEL_FORMATS; frames are mono8


class Camera(ABC):
    """One camera behind the common interface; subclasses implement the ``_hooks``."""

    kind: ClassVar[str]

    def __init__(self, config: CameraConfig) -> None:
        self.config = config
        self.camera_id = config.id
        self._lock = threading.RLock()
        self._open = False
        self._armed: TriggerMode | None = None
        self._settings: CameraSettings | None = None
        self._t_trigger = math.nan

    # ------------------------------------------------------------------ state
    @property
    def is_open(self) -> bool:
        return self._open

    @property
    def armed(self) -> TriggerMode | None:
        """The trigger mode acquisition runs in, or ``None`` when not acquiring."""
        return self._armed

    @property
    def settings(self) -> CameraSettings | None:
        """The settings last applied (what :meth:`reopen` applies again)."""
        return self._settings

    def default_settings(self) -> CameraSettings:
        """Settings from the station file: exposure, gain, full image size, mono8."""
        d = self.config.driver
        return CameraSettings(
            exposure_us=d.exposure_us,
            gain_db=d.gain_db,
            width=self.config.image_size[0],
            height=self.config.image_size[1],
            pixel_format=self.config.pixel_format,
        )

    # ------------------------------------------------------------------ public API
    def open(self) -> None:
        """Find the device by serial (or user id) and connect to it."""
        with self._lock:
            if self._open:
                return
            self._call("open", self._open_device, init=True)
            self._open = True

    def configure(
        self, settings: CameraSettings | None = None, **changes: object
    ) -> CameraSettings:
        """Apply ``settings`` (default: from the station file) with ``changes``; return them."""
        base = settings or self.default_settings()
        unknown = sorted(set(changes) - set(CameraSettings.__dataclass_fields__))
        if unknown:
            raise DriverInitError(f"camera {self.camera_id!r}: unknown settings {unknown}")
        s = replace(base, **changes)  # type: ignore[arg-type]
        if s.pixel_format.lower() not in PIXEL_FORMATS:
            raise DriverInitError(
                f"camera {self.camera_id!r}: pixel format {s.pixel_format!r} is not supported; "
                f"frames are uint8 mono, made from one of {list(PIXEL_FORMATS)}"
            )
        with self._lock:
            self._require_open("configure")
            if self._armed is not None:
                raise DriverOperationError(
                    f"camera {self.camera_id!r}: configure while armed; disarm first"
                )
            self._call("configure", lambda: self._configure(s), init=True)
            self._settings = s
        return s

    def arm(self, trigger: TriggerMode = "software") -> None:
        """Start acquisition: wait for software or hardware triggers, or run free."""
        if trigger not in TRIGGER_MODES:
            raise DriverInitError(
                f"camera {self.camera_id!r}: trigger must be one of {TRIGGER_MODES}, "
                f"got {trigger!r}"
            )
        with self._lock:
            self._require_open("arm")
            if self._settings is None:
                self.configure()
            if self._armed == trigger:
                return
            if self._armed is not None:
                self.disarm()
            self._call("arm", lambda: self._arm(trigger), init=True)
            self._armed = trigger
            self._t_trigger = math.nan

    def disarm(self) -> None:
        """Stop acquisition (the device stays open and configured)."""
        with self._lock:
            if self._armed is None:
                return
            self._armed = None
            self._call("disarm", self._disarm)

    def trigger(self) -> float:
        """Send a software trigger after dropping frames already waiting; return its time."""
        with self._lock:
            self._require_open("trigger")
            if self._armed != "software":
                raise DriverOperationError(
                    f"camera {self.camera_id!r}: trigger() needs arm('software'), "
                    f"armed is {self._armed!r}"
                )
            # Frames already queued are from before this trigger: dropping them here is the
            # defence against the stale-frame reports (harvesters #383, see docs/cameras.md).
            self._call("flush", self._flush)
            t = time.monotonic()
            self._call("trigger", self._trigger)
            self._t_trigger = t
            return t

    def grab(self, deadline_s: float) -> Frame:
        """The next frame, or :class:`DriverTimeout` once ``deadline_s`` seconds have passed."""
        if not (deadline_s >= 0 and math.isfinite(deadline_s)):
            raise ValueError(
                f"camera {self.camera_id!r}: deadline_s must be finite and >= 0, got {deadline_s}"
            )
        t_end = time.monotonic() + deadline_s
        with self._lock:
            self._require_open("grab")
            if self._armed is None:
                raise DriverOperationError(f"camera {self.camera_id!r}: grab() before arm()")
            image, frame_id, ts = self._call("grab", lambda: self._grab(t_end))
            t_received = time.monotonic()
            self._check_image(image)
            t_trigger = self._t_trigger if self._armed == "software" else math.nan
            self._t_trigger = math.nan
        return Frame(self.camera_id, image, frame_id, t_trigger, t_received, ts)

    def abort(self) -> None:
        """Drop a frame in flight (an exposure a software trigger started, not yet grabbed)
        and every frame waiting, so that the next trigger's frame is its own. The live camera
        view calls it when a station trigger preempts its grab (docs/cameras.md)."""
        with self._lock:
            if not self._open or self._armed is None:
                return
            armed = self._armed
            self._call("abort", lambda: self._abort(armed))
            self._t_trigger = math.nan

    def at_view(self, view: int) -> None:  # noqa: B027 - a no-op but for simulated cameras
        """The next trigger is for ``view`` (where a robot-mounted rig is held). A real camera
        sees whatever is in front of it; the simulated one shows that view of its scene."""

    def close(self) -> None:
        """Stop and disconnect; safe to call twice and after the device was lost."""
        with self._lock:
            if not self._open:
                return
            self._open = False
            self._armed = None
            self._settings = None  # a device opened again starts from its own state
            self._call("close", self._close)

    def reopen(self) -> None:
        """Close (ignoring errors of a lost device), open, configure and arm as before."""
        with self._lock:
            settings, armed = self._settings, self._armed
            # The old connection is gone either way; opening again is what matters.
            with contextlib.suppress(DriverError):
                self.close()
            self.open()
            self.configure(settings)
            if armed is not None:
                self.arm(armed)

    def __enter__(self) -> Camera:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if not self._open else (f"armed {self._armed}" if self._armed else "open")
        return f"<{type(self).__name__} {self.camera_id!r} {state}>"

    # ------------------------------------------------------------------ backend hooks
    @abstractmethod
    def _open_device(self) -> None:
        """Find and open the device; raise :class:`DriverInitError` naming what was looked for."""

    @abstractmethod
    def _configure(self, settings: CameraSettings) -> None:
        """Apply the settings to the (open, not acquiring) device."""

    @abstractmethod
    def _arm(self, trigger: TriggerMode) -> None:
        """Set the trigger mode and start acquisition."""

    @abstractmethod
    def _disarm(self) -> None:
        """Stop acquisition."""

    def _flush(self) -> None:  # noqa: B027 - optional hook, most backends override it
        """Drop frames that are already waiting (called right before a software trigger)."""

    def _abort(self, armed: TriggerMode) -> None:
        """Drop the frame in flight and those waiting. By default acquisition is stopped and
        started again (what discards an exposure on GigE Vision and USB3 Vision devices);
        backends with nothing in flight between calls only flush."""
        self._disarm()
        self._arm(armed)
        self._flush()

    @abstractmethod
    def _trigger(self) -> None:
        """Send one software trigger."""

    @abstractmethod
    def _grab(self, t_end: float) -> tuple[Image, int, int | None]:
        """Wait until ``t_end`` (monotonic) at most; return (mono8 image, frame id, device ns)."""

    @abstractmethod
    def _close(self) -> None:
        """Release the device; must not raise for a device that is already gone."""

    # ------------------------------------------------------------------ helpers
    def _require_open(self, what: str) -> None:
        if not self._open:
            raise DriverOperationError(f"camera {self.camera_id!r}: {what}() on a closed camera")

    def _call(self, what: str, fn: Callable[[], T], init: bool = False) -> T:
        """Run a hook; a stray non-driver exception becomes one of ours, chained."""
        try:
            return fn()
        except DriverError:
            raise
        except Exception as err:
            cls = DriverInitError if init else DriverOperationError
            raise cls(f"camera {self.camera_id!r} ({self.kind}): {what} failed: {err}") from err

    def _check_image(self, image: Image) -> None:
        s = self._settings
        want = (s.height, s.width) if s and s.width and s.height else None
        if image.dtype != np.uint8 or image.ndim != 2 or (want is not None and image.shape != want):
            shown = f"{want[1]}x{want[0]} " if want else ""
            raise FrameFormatError(
                f"camera {self.camera_id!r}: expected {shown}mono8, got {image_format(image)}"
            )

    def _full_or_region(self, image: Image, where: str = "") -> Image:
        """A recorded or simulated frame as the configured region delivers it: a frame of the
        sensor's size is cut to the region (what the device does), a frame already of the
        region's size is kept; any other size is refused, never cropped to fit."""
        s = self._settings
        if s is None or s.width is None or s.height is None:
            return image
        w, h = self.config.image_size
        region = (s.height, s.width)
        if image.shape == region:
            return image
        if image.shape != (h, w):
            shown = f"{s.width}x{s.height}" + (
                f" (region at {s.offset_x}, {s.offset_y} of {w}x{h})" if region != (h, w) else ""
            )
            raise FrameFormatError(
                f"camera {self.camera_id!r}: expected {shown} mono8, got "
                f"{image_format(image)}{where}"
            )
        return image[s.offset_y : s.offset_y + s.height, s.offset_x : s.offset_x + s.width]


def to_mono8(data: np.ndarray, pixel_format: str, width: int, height: int, camera_id: str) -> Image:
    """Turn a vendor buffer (flat or shaped) into a fresh ``[H, W]`` uint8 image, or raise.

    Always copies: the vendor buffer goes back to the driver's queue right after this call, and
    reading it later gives another frame's pixels (harvesters #234, see docs/cameras.md).
    """
    fmt = pixel_format.replace("Packed", "").lower()
    channels = {"mono8": 1, "rgba8": 4, "bgra8": 4, "rgb8": 3, "bgr8": 3}.get(fmt)
    if channels is None or data.dtype != np.uint8:
        raise DriverOperationError(
            f"camera {camera_id!r}: expected mono8 (or 8-bit RGB to convert), got "
            f"{width}x{height} {pixel_format} ({data.dtype})"
        )
    if data.size != width * height * channels:
        raise DriverOperationError(
            f"camera {camera_id!r}: {pixel_format} buffer of {data.size} bytes does not hold "
            f"{width}x{height} pixels"
        )
    a = data.reshape(height, width, channels) if channels > 1 else data.reshape(height, width)
    if fmt == "mono8":
        return np.array(a, dtype=np.uint8, copy=True)
    code = {
        "rgba8": cv2.COLOR_RGBA2GRAY,
        "bgra8": cv2.COLOR_BGRA2GRAY,
        "rgb8": cv2.COLOR_RGB2GRAY,
        "bgr8": cv2.COLOR_BGR2GRAY,
    }[fmt]
    grey: Image = cv2.cvtColor(np.ascontiguousarray(a), code).astype(np.uint8, copy=False)
    return grey


def trigger_source(config: CameraConfig, trigger: TriggerMode) -> str:
    """GenICam TriggerSource for a mode: Software, or the hardware line (features or Line1)."""
    if trigger == "software":
        return "Software"
    return str(config.driver.features.get("TriggerSource", "Line1"))


def lost(camera_id: str, kind: str, what: str, err: BaseException) -> DeviceLostError:
    """A :class:`DeviceLostError` with a message in the family's shape."""
    return DeviceLostError(f"camera {camera_id!r} ({kind}): device lost during {what}: {err}")
