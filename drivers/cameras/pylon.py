"""Basler cameras through pypylon (pylon's own transport layers: GigE, USB3, camera emulation).

pylon's camera emulation (``PYLON_CAMEMU=N`` devices, serials ``0815-0000`` …) is what the tests
use; with the features ``ImageFilename`` (a folder), ``ImageFileMode: On`` and
``TestImageSelector: Off`` from ``driver.features`` it sends the folder's images in name order,
one per trigger. Defences: ``WaitForFrameTriggerReady`` before each software trigger (a trigger
sent while the camera is not ready is silently lost), queued results drained before a trigger
(stale frames), every ``GrabResult`` released in ``finally`` (pylon's buffer pool is small), and
``RetrieveResult`` called in short slices so our deadline, not pylon's, decides.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from drivers.cameras.base import (
    Camera,
    CameraSettings,
    Image,
    TriggerMode,
    lost,
    to_mono8,
    trigger_source,
)
from drivers.errors import DriverError, DriverInitError, DriverOperationError, DriverTimeout
from mvpose_core.station import CameraConfig

log = logging.getLogger(__name__)

_RETRIEVE_SLICE_MS = 20


def _pylon() -> tuple[Any, Any]:
    from pypylon import genicam, pylon

    return pylon, genicam


class PylonCamera(Camera):
    """A Basler camera (or a pylon emulated one) found by serial number or user-defined name."""

    kind = "pylon"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._cam: Any = None
        self.unsupported: list[str] = []

    @property
    def instant_camera(self) -> Any:
        """pylon's InstantCamera (for features this interface does not cover)."""
        if self._cam is None:
            raise DriverOperationError(f"camera {self.camera_id!r}: not open")
        return self._cam

    # ------------------------------------------------------------------ hooks
    def _open_device(self) -> None:
        pylon, _ = _pylon()
        d = self.config.driver
        tlf = pylon.TlFactory.GetInstance()
        infos = list(tlf.EnumerateDevices())
        if d.serial:
            match = [i for i in infos if i.GetSerialNumber() == d.serial]
            what = f"serial {d.serial!r}"
        else:
            match = [i for i in infos if i.GetUserDefinedName() == d.user_id]
            what = f"user id {d.user_id!r}"
        if not match:
            found = [(i.GetSerialNumber(), i.GetUserDefinedName()) for i in infos]
            raise DriverInitError(
                f"camera {self.camera_id!r} (pylon): no device with {what}; "
                f"found (serial, user id) {found} (set PYLON_CAMEMU=N for emulated cameras)"
            )
        try:
            cam = pylon.InstantCamera(tlf.CreateDevice(match[0]))
            cam.Open()
        except Exception as err:
            raise DriverInitError(
                f"camera {self.camera_id!r} (pylon): cannot open {what}: {err}"
            ) from err
        self._cam = cam

    def _configure(self, s: CameraSettings) -> None:
        self.unsupported = []
        self._set("PixelFormat", s.pixel_format, required=True)
        for name in ("OffsetX", "OffsetY"):
            self._set(name, 0)  # zero first so a larger region fits
        for name, value in (("Width", s.width), ("Height", s.height)):
            if value is not None:
                self._set(name, value, required=True)
        for name, value in (("OffsetX", s.offset_x), ("OffsetY", s.offset_y)):
            if value:
                self._set(name, value, required=True)
        if s.exposure_us is not None:
            self._set("ExposureTime", s.exposure_us)
        if s.gain_db is not None:
            self._set("Gain", s.gain_db)
        for feature, setting in self.config.driver.features.items():
            self._set(feature, setting, required=True, exact=True)

    def _arm(self, trigger: TriggerMode) -> None:
        pylon, _ = _pylon()
        self._set("TriggerSelector", "FrameStart")
        self._set("TriggerMode", "Off" if trigger == "free_run" else "On", required=True)
        if trigger != "free_run":
            self._set("TriggerSource", trigger_source(self.config, trigger), required=True)
        # Free running: only the newest frame matters. Triggered: every frame, in order.
        strategy = (
            pylon.GrabStrategy_LatestImageOnly
            if trigger == "free_run"
            else pylon.GrabStrategy_OneByOne
        )
        self._cam.StartGrabbing(strategy)

    def _disarm(self) -> None:
        self._cam.StopGrabbing()

    def _flush(self) -> None:
        pylon, _ = _pylon()
        while self._cam.GetGrabResultWaitObject().Wait(0):
            r = self._cam.RetrieveResult(0, pylon.TimeoutHandling_Return)
            if r is None or not r.IsValid():
                return
            r.Release()

    def _trigger(self) -> None:
        pylon, _ = _pylon()
        wait_ms = int(self.config.driver.grab_timeout_ms)
        if not self._cam.WaitForFrameTriggerReady(wait_ms, pylon.TimeoutHandling_Return):
            raise DriverTimeout(
                f"camera {self.camera_id!r} (pylon): not ready for a trigger within {wait_ms} ms"
            )
        self._cam.ExecuteSoftwareTrigger()

    def _grab(self, t_end: float) -> tuple[Image, int, int | None]:
        pylon, genicam = _pylon()
        while True:
            remaining_ms = int((t_end - time.monotonic()) * 1000)
            if remaining_ms <= 0:
                raise DriverTimeout(
                    f"camera {self.camera_id!r} (pylon): no frame before the deadline"
                )
            try:
                r = self._cam.RetrieveResult(
                    min(remaining_ms, _RETRIEVE_SLICE_MS), pylon.TimeoutHandling_Return
                )
            except genicam.GenericException as err:
                if self._cam.IsCameraDeviceRemoved():
                    raise lost(self.camera_id, self.kind, "grab", err) from err
                raise DriverOperationError(
                    f"camera {self.camera_id!r} (pylon): grab failed: {err}"
                ) from err
            if r is None or not r.IsValid():
                if self._cam.IsCameraDeviceRemoved():
                    raise lost(self.camera_id, self.kind, "grab", RuntimeError("device removed"))
                continue
            try:
                return self._frame(r)
            finally:
                r.Release()

    def _frame(self, r: Any) -> tuple[Image, int, int | None]:
        if not r.GrabSucceeded():
            raise DriverOperationError(
                f"camera {self.camera_id!r} (pylon): frame {r.ImageNumber} failed: "
                f"{r.GetErrorCode():#x} {r.GetErrorDescription()}"
            )
        fmt = str(self._cam.GetNodeMap().GetNode("PixelFormat").ToString())
        w, h = int(r.Width), int(r.Height)
        try:
            data = r.GetArray()
        except ValueError as err:  # pypylon has no numpy layout for packed formats
            raise DriverOperationError(
                f"camera {self.camera_id!r}: expected mono8, got {w}x{h} {fmt}"
            ) from err
        ts = int(r.TimeStamp) or None  # the emulation reports 0: no clock
        return to_mono8(data, fmt, w, h, self.camera_id), int(r.ImageNumber), ts

    def _close(self) -> None:
        cam, self._cam = self._cam, None
        if cam is None:
            return
        for step in ("StopGrabbing", "Close", "DestroyDevice"):
            try:
                getattr(cam, step)()
            except Exception as err:  # a lost device fails here; the next step still runs
                log.warning("camera %r: pylon %s failed: %s", self.camera_id, step, err)

    # ------------------------------------------------------------------ node helper
    def _set(self, name: str, value: object, required: bool = False, exact: bool = False) -> None:
        _, genicam = _pylon()
        node = self._cam.GetNodeMap().GetNode(name)
        if node is None or not genicam.IsWritable(node):
            if required:
                raise DriverInitError(
                    f"camera {self.camera_id!r} (pylon): no writable feature {name!r}"
                )
            if value:
                log.warning(
                    "camera %r: device has no %s; %r not applied", self.camera_id, name, value
                )
                self.unsupported.append(name)
            return
        try:
            if isinstance(node, genicam.IEnumeration):
                options = list(node.Symbolics)
                want = str(value)
                match = [
                    o
                    for o in options
                    if o == want or (not exact and o.lower().replace("packed", "") == want.lower())
                ]
                if not match:
                    raise DriverInitError(
                        f"camera {self.camera_id!r} (pylon): {name} {want!r} not offered; "
                        f"device has {options}"
                    )
                node.Value = match[0]
            elif isinstance(node, genicam.IInteger | genicam.IFloat):
                lo, hi = node.Min, node.Max
                number = float(value)  # type: ignore[arg-type]
                if not lo <= number <= hi:
                    raise DriverInitError(
                        f"camera {self.camera_id!r} (pylon): {name} = {value} outside [{lo}, {hi}]"
                    )
                node.Value = int(number) if isinstance(node, genicam.IInteger) else number
            elif isinstance(node, genicam.ICommand):
                node.Execute()
            elif isinstance(node, genicam.IBoolean):
                node.Value = bool(value)
            else:
                node.FromString(str(value))
        except DriverError:
            raise
        except Exception as err:
            raise DriverInitError(
                f"camera {self.camera_id!r} (pylon): cannot set {name} = {value!r}: {err}"
            ) from err
