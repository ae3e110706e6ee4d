"""GenICam cameras through harvesters and a GenTL producer (.cti), e.g. GigE Vision or USB3 Vision.

harvesters is used as a library, with defences against what its maintainers' issue threads
report (docs/cameras.md lists the threads):

- ``fetch()`` blocks forever without a timeout and restarts its timer after every incomplete
  buffer: we only call ``try_fetch`` with short slices and check our own deadline between them.
- a buffer must go back to the producer's queue or acquisition starves, and its memory is
  reused once queued: we copy the pixels out and queue in ``finally``.
- frames already waiting when a trigger is sent are stale: we drain them before each trigger.
- ``update()`` invalidates every image acquirer of that Harvester, and a second Harvester on the
  same .cti sees no devices: one shared Harvester per producer file, enumerated only while no
  camera of it is open.
- ``stop``/``destroy`` may raise for a device that went away, which left the device "in use":
  close() goes through every step regardless and releases the Harvester when the last user goes.

Devices without ``TriggerSoftware`` (the viky.cti simulator runs free) get an emulated software
trigger: trigger() drops waiting frames, and grab returns the first frame that arrives after it.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
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

# try_fetch slices: short enough that the deadline is checked often, long enough to not spin.
_FETCH_SLICE_S = 0.02
_DRAIN_SLICE_S = 0.0005


@dataclass
class _Producer:
    harvester: Any
    users: int = 0


# One Harvester per .cti file in this process: the GenTL producer is a shared library that a
# second Harvester cannot enumerate again, so cameras of one producer must share it.
_producers: dict[str, _Producer] = {}
_producers_lock = threading.Lock()


def _acquire_producer(cti: str) -> Any:
    from harvesters.core import Harvester

    with _producers_lock:
        p = _producers.get(cti)
        if p is None:
            h = Harvester()
            h.add_file(cti, check_existence=True, check_validity=True)
            p = _producers[cti] = _Producer(h)
        if p.users == 0:
            p.harvester.update()  # safe only now: update() invalidates open acquirers
        p.users += 1
        return p.harvester


def _release_producer(cti: str) -> None:
    with _producers_lock:
        p = _producers.get(cti)
        if p is None:
            return
        p.users -= 1
        if p.users <= 0:
            del _producers[cti]
            try:
                p.harvester.reset()
            except Exception as err:  # a producer that fails to unload must not stop the close
                log.warning("harvesters reset of %s failed: %s", cti, err)


def _info(info: Any, field: str) -> str | None:
    """A device-info field, or None where the producer does not report it (viky: user id)."""
    try:
        value = getattr(info, field)
    except Exception:
        return None
    return None if value is None else str(value)


class GenICamCamera(Camera):
    """A GenTL device found by serial number or user-defined name."""

    kind = "genicam"

    def __init__(self, config: CameraConfig) -> None:
        super().__init__(config)
        self._cti = ""
        self._ia: Any = None
        self._emulated_trigger = False
        self._emulated_pending = 0  # emulated software triggers not yet answered
        self.unsupported: list[str] = []  # settings the device has no feature for

    @property
    def node_map(self) -> Any:
        """The device's GenICam node map (for features this interface does not cover)."""
        if self._ia is None:
            raise DriverOperationError(f"camera {self.camera_id!r}: not open")
        return self._ia.remote_device.node_map

    @property
    def trigger_emulated(self) -> bool:
        """True when the device runs free and software triggers are emulated."""
        return self._emulated_trigger

    # ------------------------------------------------------------------ hooks
    def _open_device(self) -> None:
        d = self.config.driver
        if not d.cti:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): driver.cti (the GenTL producer) is not set"
            )
        cti = str(Path(d.cti).resolve())
        if not Path(cti).is_file():
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): GenTL producer {d.cti!r} not found"
            )
        try:
            h = _acquire_producer(cti)
        except Exception as err:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): cannot load {d.cti!r}: {err}"
            ) from err
        self._cti = cti
        try:
            with _producers_lock:  # CaptureGroup workers open cameras of one producer at once
                self._ia = self._create(h)
        except BaseException:
            self._cti = ""
            _release_producer(cti)
            raise

    def _create(self, h: Any) -> Any:
        d = self.config.driver
        key = {"serial_number": d.serial} if d.serial else {"user_defined_name": d.user_id}
        infos = list(h.device_info_list)
        if not any(_info(i, k) == v for i in infos for k, v in key.items()):
            found = [(_info(i, "serial_number"), _info(i, "user_defined_name")) for i in infos]
            what = f"serial {d.serial!r}" if d.serial else f"user id {d.user_id!r}"
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): no device with {what} on "
                f"{Path(self._cti).name}; found (serial, user id) {found}"
            )
        try:
            return h.create(key)
        except Exception as err:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): cannot open {key}: "
                f"{type(err).__name__}: {err}"
            ) from err

    def _configure(self, s: CameraSettings) -> None:
        nm = self.node_map
        self.unsupported = []
        self._set_enum(nm, "PixelFormat", s.pixel_format, required=True)
        for name in ("OffsetX", "OffsetY"):
            self._set_number(nm, name, 0)  # zero first so a larger region fits
        for name, size in (("Width", s.width), ("Height", s.height)):
            if size is not None:
                self._set_number(nm, name, size, required=True)
        for name, offset in (("OffsetX", s.offset_x), ("OffsetY", s.offset_y)):
            if offset:
                self._set_number(nm, name, offset, required=True)
        if s.exposure_us is not None:
            self._set_number(nm, "ExposureTime", s.exposure_us)
        if s.gain_db is not None:
            self._set_number(nm, "Gain", s.gain_db)
        for name, value in self.config.driver.features.items():
            if not nm.has_node(name):
                raise DriverInitError(
                    f"camera {self.camera_id!r} (genicam): device has no feature {name!r}"
                )
            self._write(nm.get_node(name), name, value)

    def _arm(self, trigger: TriggerMode) -> None:
        nm = self.node_map
        has_trigger = nm.has_node("TriggerMode") and nm.has_node("TriggerSoftware")
        self._emulated_trigger = trigger == "software" and not has_trigger
        if trigger == "hardware" and not nm.has_node("TriggerMode"):
            raise DriverInitError(f"camera {self.camera_id!r} (genicam): device has no TriggerMode")
        if nm.has_node("TriggerMode"):
            if nm.has_node("TriggerSelector"):
                self._set_enum(nm, "TriggerSelector", "FrameStart")
            self._set_enum(
                nm, "TriggerMode", "Off" if trigger == "free_run" else "On", required=True
            )
            if trigger != "free_run":
                source = trigger_source(self.config, trigger)
                self._set_enum(nm, "TriggerSource", source, required=True)
        if self._emulated_trigger and nm.has_node("AcquisitionFrameRate"):
            # The "triggered" frame is the next one the device sends: make it come soon.
            node = nm.AcquisitionFrameRate
            node.value = node.max
        self._emulated_pending = 0
        self._ia.start()

    def _disarm(self) -> None:
        self._ia.stop()

    def _flush(self) -> None:
        self._emulated_pending = 0
        for _ in range(self._ia.num_buffers + 2):
            buf = self._ia.try_fetch(timeout=_DRAIN_SLICE_S)
            if buf is None:
                return
            buf.queue()

    def _abort(self, armed: TriggerMode) -> None:
        if self._emulated_trigger:
            self._flush()  # a free-running device: no exposure of ours in flight, only frames
        else:
            super()._abort(armed)

    def _trigger(self) -> None:
        if self._emulated_trigger:
            self._emulated_pending += 1
        else:
            self.node_map.TriggerSoftware.execute()

    def _grab(self, t_end: float) -> tuple[Image, int, int | None]:
        from genicam.gentl import GenericException as GenTLError

        if self._emulated_trigger and self._emulated_pending == 0:
            # Same contract as a triggered device: no trigger, no frame.
            time.sleep(max(0.0, t_end - time.monotonic()))
            raise DriverTimeout(
                f"camera {self.camera_id!r} (genicam): no trigger before the deadline"
            )
        while True:
            remaining = t_end - time.monotonic()
            if remaining <= 0:
                raise DriverTimeout(
                    f"camera {self.camera_id!r} (genicam): no frame before the deadline"
                )
            try:
                buf = self._ia.try_fetch(timeout=min(remaining, _FETCH_SLICE_S))
            except GenTLError as err:
                raise lost(self.camera_id, self.kind, "fetch", err) from err
            if buf is None:
                continue
            try:
                c = buf.payload.components[0]
                image = to_mono8(c.data, c.data_format, c.width, c.height, self.camera_id)
                frame_id = int(buf.frame_id)
                try:
                    ts: int | None = int(buf.timestamp_ns)
                except GenTLError:
                    ts = None  # viky.cti and some producers report no timestamps
            finally:
                buf.queue()
            self._emulated_pending = max(0, self._emulated_pending - 1)
            return image, frame_id, ts

    def _close(self) -> None:
        ia, cti = self._ia, self._cti
        self._ia, self._cti = None, ""
        for step in ("stop", "destroy"):
            if ia is None:
                break
            try:
                getattr(ia, step)()
            except Exception as err:  # a lost device fails here; the next step still runs
                log.warning("camera %r: harvesters %s failed: %s", self.camera_id, step, err)
        if cti:
            _release_producer(cti)

    # ------------------------------------------------------------------ node helpers
    def _set_enum(self, nm: Any, name: str, value: str, required: bool = False) -> None:
        if not nm.has_node(name):
            self._missing(name, value, required)
            return
        node = nm.get_node(name)
        options = list(node.symbolics)
        match = [o for o in options if o.lower().replace("packed", "") == value.lower()]
        if not match:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): {name} {value!r} not offered; "
                f"device has {options}"
            )
        self._write(node, name, match[0])

    def _set_number(self, nm: Any, name: str, value: float, required: bool = False) -> None:
        if not nm.has_node(name):
            self._missing(name, value, required)
            return
        node = nm.get_node(name)
        lo, hi = node.min, node.max
        if not lo <= value <= hi:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): {name} = {value} outside [{lo}, {hi}]"
            )
        self._write(node, name, type(node.value)(value))

    def _write(self, node: Any, name: str, value: object) -> None:
        try:
            node.value = value
        except DriverError:
            raise
        except Exception as err:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): cannot set {name} = {value!r}: {err}"
            ) from err

    def _missing(self, name: str, value: object, required: bool) -> None:
        if required:
            raise DriverInitError(
                f"camera {self.camera_id!r} (genicam): device has no {name} feature"
            )
        if value:  # asking for a non-default value the device cannot take is worth a warning
            log.warning("camera %r: device has no %s; %r not applied", self.camera_id, name, value)
            self.unsupported.append(name)
