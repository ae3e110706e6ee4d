"""Cameras behind one interface: pick the backend from the station file and open it.

The table maps ``driver.kind`` to ``(module, class)`` and imports a backend only when a station
uses it (python-can's ``BACKENDS`` idea), so a station with simulated cameras never loads pylon
or a GenTL producer. See docs/cameras.md for each backend and its emulator.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from drivers.cameras.base import (
    PIXEL_FORMATS,
    TRIGGER_MODES,
    Camera,
    CameraSettings,
    Frame,
    TriggerMode,
)
from drivers.cameras.capture import Backoff, CaptureGroup
from drivers.errors import (
    DeviceLostError,
    DriverError,
    DriverInitError,
    DriverOperationError,
    DriverTimeout,
)
from mvpose_core.station import CameraConfig, StationConfig

if TYPE_CHECKING:
    from drivers.cameras.sim import RenderOptions, SimScene

# kind -> (module, class); every class takes (config) and the sim one also (config, scene).
BACKENDS: dict[str, tuple[str, str]] = {
    "sim": ("drivers.cameras.sim", "SimCamera"),
    "genicam": ("drivers.cameras.genicam", "GenICamCamera"),
    "pylon": ("drivers.cameras.pylon", "PylonCamera"),
    "files": ("drivers.cameras.files", "FilesCamera"),
}


def backend_class(kind: str) -> type[Camera]:
    """The camera class for a driver kind, imported on first use."""
    try:
        module_name, class_name = BACKENDS[kind]
    except KeyError:
        raise DriverInitError(
            f"unknown camera driver kind {kind!r}; known: {sorted(BACKENDS)}"
        ) from None
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise DriverInitError(
            f"camera driver {kind!r} needs a package that is not installed: {err}"
        ) from err
    cls: type[Camera] = getattr(module, class_name)
    return cls


def make_camera(config: CameraConfig, scene: SimScene | None = None) -> Camera:
    """The camera object for ``config`` (not yet connected)."""
    cls = backend_class(config.driver.kind)
    if config.driver.kind == "sim":
        if scene is None:
            raise DriverInitError(f"camera {config.id!r}: a sim camera needs a SimScene to look at")
        return cls(config, scene)  # type: ignore[call-arg]
    return cls(config)


def open_camera(config: CameraConfig, scene: SimScene | None = None) -> Camera:
    """Make the camera for ``config`` (backend by ``config.driver.kind``) and open it."""
    cam = make_camera(config, scene)
    cam.open()
    return cam


def capture_station(
    station: StationConfig,
    scene: SimScene | None = None,
    *,
    trigger: TriggerMode = "software",
    backoff: Backoff | None = None,
) -> CaptureGroup:
    """A CaptureGroup of every camera of a station; the workers open and arm them."""
    cameras = [make_camera(c, scene) for c in station.cameras]
    return CaptureGroup(cameras, trigger=trigger, backoff=backoff)


def __getattr__(name: str) -> Any:
    # The simulator pulls in the renderer; load it only when someone asks for it.
    if name in ("SimScene", "RenderOptions"):
        return getattr(importlib.import_module("drivers.cameras.sim"), name)
    raise AttributeError(f"module 'drivers.cameras' has no attribute {name!r}")


__all__ = [
    "BACKENDS",
    "PIXEL_FORMATS",
    "TRIGGER_MODES",
    "Backoff",
    "Camera",
    "CameraSettings",
    "CaptureGroup",
    "DeviceLostError",
    "DriverError",
    "DriverInitError",
    "DriverOperationError",
    "DriverTimeout",
    "Frame",
    "RenderOptions",
    "SimScene",
    "TriggerMode",
    "backend_class",
    "capture_station",
    "make_camera",
    "open_camera",
]
