"""Simulated cameras: a scene rendered from the station file, with latency and injected faults.

A :class:`SimScene` is what the simulated cameras look at. ``set_part_pose`` renders every
camera of every view at once (as a real part is in the cell before the trigger) with
:func:`mvpose_core.render.render_view`, and caches the frames; a :class:`SimCamera` then hands
out the cached frame of its camera at the scene's current view, after ``driver.latency_ms``. The
view is the one each trigger names: the capture tells the cameras (``Camera.at_view``), so view
k's grab shows view k in every mode, not only in the demo.
Frames are shared read-only arrays, so a grab costs no copy (benchmarks use ``set_frames``
with pre-rendered images). Image noise is drawn once per pose, not per grab. With ``keep_poses``
the scene keeps the renderings of that many recent poses: a part moved back to one of them
(a served station's benchmark cycling its part over the tolerance) is there at once.

Faults come from ``driver.fault`` (every n-th grab): ``timeout`` (no frame before the deadline),
``disconnect`` (:class:`DeviceLostError`; the camera cannot be opened for ``fault.down_ms``) and
``corrupt`` (a frame the transport flags as incomplete, as pylon's ``GrabSucceeded()`` does).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from dataclasses import replace

import numpy as np

from drivers.cameras.base import Camera, CameraSettings, Image, TriggerMode
from drivers.errors import DeviceLostError, DriverInitError, DriverOperationError, DriverTimeout
from mvpose_core.render import RenderedImage, RenderOptions, render_view
from mvpose_core.scene import ViewCamera, view_cameras
from mvpose_core.station import CameraConfig, RecipeConfig, StationConfig
from mvpose_core.transforms import Array

__all__ = ["RenderOptions", "SimCamera", "SimScene"]


def _frozen(image: np.ndarray) -> Image:
    a = np.ascontiguousarray(image, dtype=np.uint8)
    a.flags.writeable = False
    return a


class SimScene:
    """The part, the views and the rendered frames the simulated cameras deliver."""

    def __init__(
        self,
        station: StationConfig,
        recipe: RecipeConfig | str | None,
        rng: np.random.Generator,
        options: RenderOptions | None = None,
        keep_poses: int = 0,
    ) -> None:
        if keep_poses < 0:
            raise ValueError(f"keep_poses must be >= 0, got {keep_poses}")
        self.station = station
        self.keep_poses = keep_poses
        # renderings of recent poses, oldest first: (pose, flange poses) bytes -> frames
        self._kept: dict[bytes, dict[tuple[int, str], RenderedImage]] = {}
        self.recipe = recipe if isinstance(recipe, RecipeConfig) else station.recipe(recipe)
        self.rng = rng
        self.options = options or RenderOptions()
        self._lock = threading.Lock()
        self._hw_trigger = threading.Condition(self._lock)
        self._hw_count = 0
        self._view = station.views[0].id
        self._flange: dict[int, Array] = {}
        self._T_rf_from_pf: Array | None = None
        self._frames: dict[tuple[int, str], Image] = {}
        self._truth: dict[tuple[int, str], RenderedImage] = {}

    # ------------------------------------------------------------------ what the test sets
    @property
    def view(self) -> int:
        return self._view

    @property
    def T_rf_from_pf(self) -> Array | None:
        return self._T_rf_from_pf

    def set_part_pose(self, T_rf_from_pf: Array) -> None:
        """Put the part at ``T_rf_from_pf`` and render every camera of every view now (or take
        the kept rendering of that pose, see ``keep_poses``)."""
        T = np.asarray(T_rf_from_pf, dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"T_rf_from_pf must be [4, 4], got {list(T.shape)}")
        key = T.tobytes() + b"".join(
            v.to_bytes(4, "little") + f.tobytes() for v, f in sorted(self._flange.items()))
        rendered = self._kept.pop(key, None)
        if rendered is None:
            rendered = self._render(T, view_cameras(self.station, self._flange))
        if self.keep_poses:
            self._kept[key] = rendered  # the newest last
            while len(self._kept) > self.keep_poses:
                del self._kept[next(iter(self._kept))]
        with self._lock:
            self._T_rf_from_pf = T
            self._truth = dict(rendered)  # set_view re-renders views in this one, not the kept
            self._frames = {k: _frozen(r.image) for k, r in rendered.items()}

    def set_view(self, view_id: int, T_rf_from_gf: Array | None = None) -> None:
        """Move to a view; with the robot's actual flange pose, render that view again."""
        self.station.view(view_id)  # KeyError naming the view when it does not exist
        if T_rf_from_gf is not None:
            self._flange[view_id] = np.asarray(T_rf_from_gf, dtype=float)
            if self._T_rf_from_pf is not None:
                cams = view_cameras(self.station, self._flange, views=[view_id])
                rendered = self._render(self._T_rf_from_pf, cams)
                with self._lock:
                    self._truth.update(rendered)
                    self._frames.update({k: _frozen(r.image) for k, r in rendered.items()})
        with self._lock:
            self._view = view_id

    def set_frames(self, frames: Mapping[str, np.ndarray], view_id: int | None = None) -> None:
        """Use given images (camera id -> uint8 [H, W]) for a view: pre-rendered frames."""
        view = self._view if view_id is None else view_id
        with self._lock:
            for cid, image in frames.items():
                self._frames[(view, cid)] = _frozen(image)

    def hardware_trigger(self) -> None:
        """Pulse the trigger line of every camera armed for a hardware trigger."""
        with self._hw_trigger:
            self._hw_count += 1
            self._hw_trigger.notify_all()

    def truth(self, camera_id: str, view_id: int | None = None) -> RenderedImage:
        """The rendering (image and true mark centres) behind a camera's current frame."""
        with self._lock:
            return self._truth[(self._view if view_id is None else view_id, camera_id)]

    # ------------------------------------------------------------------ what cameras read
    def frame(self, camera_id: str) -> Image:
        with self._lock:
            image = self._frames.get((self._view, camera_id))
            if image is None:
                raise DriverOperationError(
                    f"camera {camera_id!r} (sim): nothing to see in view {self._view}; "
                    f"call SimScene.set_part_pose() or set_frames() first"
                )
            return image

    def wait_hardware_trigger(self, seen: int, t_end: float) -> int | None:
        """Block until a trigger after ``seen`` arrives or ``t_end``; the new count or None."""
        with self._hw_trigger:
            while self._hw_count <= seen:
                remaining = t_end - time.monotonic()
                if remaining <= 0:
                    return None
                self._hw_trigger.wait(remaining)
            return self._hw_count

    @property
    def hardware_count(self) -> int:
        with self._lock:
            return self._hw_count

    def _render(self, T: Array, cams: list[ViewCamera]) -> dict[tuple[int, str], RenderedImage]:
        out = {}
        for vc in cams:
            cfg = self.station.camera(vc.camera_id)
            options = replace(self.options, noise_sigma=cfg.driver.image_noise)
            out[(vc.view, vc.camera_id)] = render_view(vc, self.recipe, T, self.rng, options)
        return out


class SimCamera(Camera):
    """A camera of the station file that looks at a :class:`SimScene`."""

    kind = "sim"

    def __init__(self, config: CameraConfig, scene: SimScene) -> None:
        super().__init__(config)
        self.scene = scene
        self._trigger_mode: TriggerMode = "software"
        self._pending: list[float] = []  # trigger times not yet answered
        self._hw_seen = 0
        self._grabs = 0
        self._frame_id = 0
        self._down_until = 0.0
        self._roi = CameraSettings()

    def at_view(self, view: int) -> None:
        """Show ``view`` of the scene: its frames as rendered for that view's flange pose."""
        if view != self.scene.view:
            self.scene.set_view(view)

    def _open_device(self) -> None:
        wait = self._down_until - time.monotonic()
        if wait > 0:
            raise DriverInitError(
                f"camera {self.camera_id!r} (sim): device not reachable (back in {wait:.2f} s)"
            )
        d = self.config.driver
        known = {c.id: c.driver for c in self.scene.station.cameras}
        if self.camera_id not in known or (d.serial and known[self.camera_id].serial != d.serial):
            found = sorted((c.driver.serial or "") for c in self.scene.station.cameras)
            raise DriverInitError(
                f"camera {self.camera_id!r} (sim): no device with serial {d.serial!r} in station "
                f"{self.scene.station.name!r}; found {found}"
            )
        self._frame_id = 0

    def _configure(self, settings: CameraSettings) -> None:
        w, h = self.config.image_size
        s = settings
        if (
            s.width is not None
            and s.height is not None
            and (s.offset_x + s.width > w or s.offset_y + s.height > h)
        ):
            raise DriverInitError(
                f"camera {self.camera_id!r} (sim): region {s.width}x{s.height} at "
                f"({s.offset_x}, {s.offset_y}) outside the {w}x{h} sensor"
            )
        self._roi = settings

    def _arm(self, trigger: TriggerMode) -> None:
        self._trigger_mode = trigger
        self._pending = []
        self._hw_seen = self.scene.hardware_count

    def _disarm(self) -> None:
        self._pending = []

    def _flush(self) -> None:
        self._pending = []

    def _abort(self, armed: TriggerMode) -> None:
        self._pending = []  # nothing is in flight between calls: the queue is all there is

    def _trigger(self) -> None:
        self._pending.append(time.monotonic())

    def _grab(self, t_end: float) -> tuple[Image, int, int | None]:
        latency = self.config.driver.latency_ms / 1000.0
        if self._trigger_mode == "software":
            if not self._pending:
                return self._time_out(t_end, "no trigger")
            t_ready = self._pending[0] + latency
        elif self._trigger_mode == "hardware":
            count = self.scene.wait_hardware_trigger(self._hw_seen, t_end)
            if count is None:
                raise DriverTimeout(
                    f"camera {self.camera_id!r} (sim): no hardware trigger before the deadline"
                )
            self._hw_seen = count
            t_ready = time.monotonic() + latency
        else:
            t_ready = time.monotonic() + latency
        if t_ready > t_end:
            return self._time_out(t_end, f"frame ready {1000 * (t_ready - t_end):.1f} ms after")
        self._grabs += 1
        fault = self.config.driver.fault
        if fault.kind != "none" and fault.every_n and self._grabs % fault.every_n == 0:
            self._inject(fault.kind, t_end, fault.down_ms / 1000.0)
        image = self.scene.frame(self.camera_id)
        wait = t_ready - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # exposure + transfer time of the simulated camera
        if self._pending:
            self._pending.pop(0)
        self._frame_id += 1
        return self._crop(image), self._frame_id, time.monotonic_ns()

    def _inject(self, kind: str, t_end: float, down_s: float) -> None:
        self._pending = self._pending[1:]
        if kind == "timeout":
            self._time_out(t_end, "simulated timeout")
        if kind == "disconnect":
            self._down_until = time.monotonic() + down_s
            raise DeviceLostError(
                f"camera {self.camera_id!r} (sim): device lost during grab (simulated)"
            )
        self._frame_id += 1
        raise DriverOperationError(
            f"camera {self.camera_id!r} (sim): frame {self._frame_id} incomplete "
            "(simulated corruption)"
        )

    def _time_out(self, t_end: float, why: str) -> tuple[Image, int, int | None]:
        time.sleep(max(0.0, t_end - time.monotonic()))  # a real camera says nothing until then
        raise DriverTimeout(f"camera {self.camera_id!r} (sim): {why} before the deadline")

    def _crop(self, image: Image) -> Image:
        return self._full_or_region(image)

    def _close(self) -> None:
        self._pending = []
