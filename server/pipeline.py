"""The per-trigger pipeline: parallel capture, window detection, measure + gate → a verdict.

One trigger, in order (every stage timed, the times go into the record)::

    capture   every camera of the view at once (CaptureGroup, one deadline)
    detect    each image in windows predicted from the recipe at the taught reference pose
              (first near where the last good part was, when it sat away from the reference):
              the windows searched (on the trigger thread, or detection threads or processes),
              then every candidate of every image measured in one batch
    measure   estimate + offset + uncertainty + gate (mvpose_core.measure) from every observation
              of every view gathered so far
    correct   the perspective correction of each centre recomputed at the estimated pose (detect
              applied it at the prior pose), and the pose measured again if any correction moved
              by more than PipelineOptions.recorrect_px (see docs/detection.md)

The result is a :class:`StationResult` in the station's terms (full-precision pose, one reason
code); the audit record is built from it by server.station.records and appended by the station
(server.station.core) before any link sees the answer. The deadline (``station.deadline_ms``)
runs from the moment the trigger was taken; the verdict keeps the recent append time in reserve,
so a result that cannot reach the link in time becomes DEADLINE_EXCEEDED in the record *and* on
the link, never a late offset. Everything here is blocking and runs on the station's trigger
thread, never on an event loop.
"""

from __future__ import annotations

import logging
import math
import os
import statistics
import time
from collections import deque
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from drivers.cameras import CaptureGroup, DriverError, Frame
from drivers.errors import FrameFormatError
from mvpose_core.detect import (
    DetectOptions,
    MarkDetection,
    check_image,
    corrected,
    corrections_at,
    detect_marks_many,
)
from mvpose_core.detect.follow import next_near
from mvpose_core.detect.settle import sensitivities
from mvpose_core.estimate import EstimateOptions, Observation, PoseInputError
from mvpose_core.measure import Measurement, measure
from mvpose_core.reasons import Reason
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.robust import observations_of
from mvpose_core.scene import ViewCamera, repose, sighted_marks, view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.synth import synthetic_observations
from mvpose_core.transforms import Array
from server.detect_pool import DetectPool
from server.recipes import ActiveRecipe

log = logging.getLogger(__name__)


def auto_detect_processes() -> int:
    """Detection processes for this machine: none below 8 cores, else 4.

    A worker detects one image alone: its own measuring batch, and a part beyond the first
    windows followed from that image's blobs only (station 1's cameras see two marks each, too
    few for a pose, so the image is searched over the whole tolerance). The four images cost
    2.0x (at the reference) to 2.65x (displaced by 0.9 of the tolerance) the CPU of detecting
    them together on the trigger thread (``python -m bench.detect_alone``). Shared out over two
    workers, that is at best the trigger thread's time at the reference and 1.3x it for a
    displaced part; over four, half of it at the reference and about the same displaced.
    """
    cores = os.cpu_count() or 1
    return 0 if cores < 8 else 4


@dataclass(frozen=True)
class PipelineOptions:
    # Detection applies the perspective correction at the recipe's prior pose (free: it comes
    # with the window prediction); the correction at the estimate is then computed, and the
    # pose measured again only if some correction moved by more than ``recorrect_px``.
    detect: DetectOptions = DetectOptions(correct_perspective=True)
    estimate: EstimateOptions = EstimateOptions()
    # Threads for the detection's window search when detect_processes is 0; 0 = on the trigger
    # thread. On the 2-core machine the trigger thread was faster (six A/B pairs of `bench
    # station`, docs/performance.md): the threads mostly wait for each other's GIL.
    detect_workers: int = 0
    # Worker processes for detection (server.detect_pool), each detecting one image alone;
    # 0 = in this process (`mvpose serve`: auto_detect_processes()).
    detect_processes: int = 0
    recorrect: bool = True  # the correction at the estimated pose (second pass if it matters)
    # A second pass only when a correction changed by more than this. 0.01 px is about the
    # detector's own centre noise at image noise σ = 2 grey levels (REFERENCE.md); station 1's
    # parts within ±20 mm / ±2° of the taught pose change it by at most ~0.01 px, the whole
    # tolerance (±100 mm / ±10°) by up to ~0.05 px (python -m bench.correction_shift). 0: always.
    recorrect_px: float = 0.01
    store_reserve_ms: float = 3.0  # at least this much of the deadline is kept for the write
    capture_share: float = 0.6  # the capture may use at most this share of the deadline


@dataclass
class ViewCapture:
    """What one view contributed: detections per camera, the frames, and failures."""

    view: int
    trigger_id: int
    flange_pose: Array | None
    cameras: dict[str, ViewCamera]
    detections: dict[str, list[MarkDetection]] = field(default_factory=dict)
    camera_errors: dict[str, str] = field(default_factory=dict)
    refused: set[str] = field(default_factory=set)  # cameras whose frame had the wrong format
    frames: dict[str, np.ndarray] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)

    def observations(self) -> list[Observation]:
        """The found marks, each with its next candidates (the robust rule's alternates)."""
        return observations_of(self.view, self.detections)


@dataclass(frozen=True)
class StationResult:
    """The station's verdict on one trigger (every view gathered), before it is recorded."""

    code: int  # mvpose_core.reasons.Reason
    message: str
    measurement: Measurement | None
    views: tuple[ViewCapture, ...]
    timings_ms: dict[str, float]
    frames: dict[tuple[int, str], np.ndarray]
    observations: tuple[Observation, ...] = ()  # what the last measure() call was given

    @property
    def ok(self) -> bool:
        return self.code == 0


class Pipeline:
    """Runs triggers of one station; owns a small pool for per-image detection."""

    def __init__(
        self,
        station: StationConfig,
        capture: CaptureGroup,
        options: PipelineOptions = PipelineOptions(),  # noqa: B008 - frozen
    ) -> None:
        self.station = station
        self.capture = capture
        self.options = options
        self.deadline_s = station.deadline_ms / 1000.0
        self._pool = (ThreadPoolExecutor(options.detect_workers, thread_name_prefix="detect")
                      if options.detect_workers > 0 else None)
        # how detect_marks_many searches a view's images: on the pool, or on the calling thread
        self._map = self._pool.map if self._pool is not None else map
        self._procs = DetectPool(options.detect_processes) if options.detect_processes else None
        self._taught = {(vc.view, vc.camera_id): vc for vc in view_cameras(station)}
        self._store_ms: deque[float] = deque(maxlen=50)
        # The last good part's recipe, where the next trigger's first windows are searched (None:
        # the prior; mvpose_core.detect.follow.next_near) and the part's pose. Trigger thread only.
        self._near: tuple[RecipeConfig, Array | None, Array] | None = None

    def warm_up(self, recipe: RecipeConfig, passes: int = 8) -> None:
        """Run a trigger's computations on made-up input before the station is ready (nothing
        is captured or stored): each camera's view of the recipe's marks at the taught pose,
        rendered without noise, detected, measured and corrected as a trigger would, ``passes``
        times, so that the first real trigger finds every cache filled (window predictions,
        layouts, the fine pass's ray tables, the estimator's tables), every code path of
        numpy, OpenCV and scipy loaded, and the interpreter's specialised bytecode in place
        (CPython specialises a function after it ran about eight times). A view that cannot
        be rendered falls back to blank frames and the recipe's own marks projected (the
        measurement part still runs)."""
        prior = recipe.T_rf_from_pf0.matrix
        rng = np.random.default_rng(0)
        clean = RenderOptions(noise_sigma=0.0, shot_noise_gain=0.0, supersample=4)
        frames: list[tuple[np.ndarray, ViewCamera]] = []
        for view in sorted({s.view for s in recipe.sightings}):
            for cid, vc in self.view_cameras(view, None).items():
                if not sighted_marks(recipe, view, cid):
                    continue
                try:
                    image = render_view(vc, recipe, prior, rng, clean).image
                except Exception:  # noqa: BLE001 - the warm-up must not stop a start
                    image = np.zeros((vc.model.height, vc.model.width), np.uint8)
                frames.append((image, vc))
        cams = [vc for _, vc in frames]
        # how the marks' images and corrections move with the pose at the reference (a part
        # found off it in the first windows is corrected at its own pose when that matters)
        sensitivities(cams, recipe, prior)
        for _ in range(passes):
            found = detect_marks_many(frames, recipe, prior, self.options.detect,
                                      map_fn=self._map)
            groups = [(vc, dets) for (_, vc), dets in zip(frames, found, strict=True)]
            obs = [o for vc, dets in groups for o in observations_of(vc.view, {vc.camera_id: dets})]
            if len(obs) < 3:  # nothing rendered: the recipe's marks projected instead
                obs = synthetic_observations(self.station, recipe, prior,
                                             np.random.default_rng(0), 0.0,
                                             require_in_image=False)
            meas = measure(self.station, recipe, obs, None, self.options.estimate, cameras=cams)
            corrected(groups, corrections_at(groups, recipe, meas.T_rf_from_pf)[0])

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        if self._procs is not None:
            self._procs.close()

    # ------------------------------------------------------------------ capture + detect
    def view_cameras(self, view: int, flange_pose: Array | None) -> dict[str, ViewCamera]:
        """The view's cameras, posed with the robot's actual flange pose when it sent one."""
        taught = {cid: vc for (v, cid), vc in self._taught.items() if v == view}
        if flange_pose is None:
            return taught
        # The taught cameras moved, not built anew: each keeps its lens model, and what the
        # detector remembers per camera place is re-posed (mvpose_core.detect.geometry).
        return {vc.camera_id: vc for vc in
                repose(list(taught.values()), self.station, {view: flange_pose})}

    def capture_view(
        self, view: int, trigger_id: int, recipe: RecipeConfig, flange_pose: Array | None,
        t0: float,
    ) -> ViewCapture:
        """Grab every camera and detect the recipe's marks in the cameras of ``view``."""
        cams = self.view_cameras(view, flange_pose)
        vcap = ViewCapture(view=view, trigger_id=trigger_id, flange_pose=flange_pose, cameras=cams)
        budget = max(0.001, self.deadline_s * self.options.capture_share - (time.monotonic() - t0))
        t = time.monotonic()
        try:
            grabbed: dict[str, object] = dict(self.capture.grab_all(budget, camera_ids=list(cams),
                                                                    view=view))
        except DriverError as group_err:  # the group itself failed: so did each of its cameras
            grabbed = {cid: group_err for cid in cams}
        vcap.timings_ms["capture"] = (time.monotonic() - t) * 1e3
        self.detect_view(vcap, grabbed, recipe)
        return vcap

    def detect_view(self, vcap: ViewCapture, grabbed: dict[str, object],
                    recipe: RecipeConfig) -> None:
        """Detect the recipe's marks in a view's frames: ``grabbed`` maps each camera id to its
        :class:`Frame` or the :class:`DriverError` that replaced it (``mvpose measure`` passes
        frames read from files)."""
        cams = vcap.cameras
        view = vcap.view
        prior = recipe.T_rf_from_pf0.matrix
        jobs = {}
        batch: list[tuple[str, np.ndarray, ViewCamera]] = []
        near = self._near[1] if self._near is not None and self._near[0] is recipe else None
        t = time.monotonic()
        for cid, vc in cams.items():
            res = grabbed.get(cid)
            if not sighted_marks(recipe, view, cid):
                continue  # this camera sees nothing of this part in this view
            if isinstance(res, Frame):
                vcap.frames[cid] = res.image
                try:  # a bad image fails its own camera only, with the detector's words
                    image = check_image(res.image, vc.model, f"camera {vc.key!r}")
                except ValueError as err:
                    self._detect_failed(vcap, recipe, cid, err)
                    continue
                if self._procs is not None:
                    jobs[cid] = self._procs.submit(vc, image, recipe, prior, self.options.detect,
                                                   near)
                else:
                    batch.append((cid, image, vc))
            elif isinstance(res, FrameFormatError):  # a frame of the wrong format: never
                self._detect_failed(vcap, recipe, cid, res)  # cropped, DETECTION_FAILED
            else:
                failed = res if isinstance(res, DriverError) else DriverError(
                    f"camera {cid!r}: no result")
                vcap.camera_errors[cid] = str(failed)
                vcap.detections[cid] = [
                    MarkDetection.missing(m, f"camera: {failed}")
                    for m in sighted_marks(recipe, view, cid)
                ]
        if batch:
            # One call for the view's images: their windows are searched on the pool's
            # threads, and all their candidates measured in one batch (mvpose_core.detect).
            found = detect_marks_many([(img, vc) for _, img, vc in batch], recipe, prior,
                                      self.options.detect, map_fn=self._map, near=near)
            for (cid, _, _), dets in zip(batch, found, strict=True):
                vcap.detections[cid] = dets
        for cid, fut in jobs.items():
            try:
                vcap.detections[cid] = fut.result()
            except ValueError as err:  # the detector's refusal of a bad image names the problem
                self._detect_failed(vcap, recipe, cid, err)
        vcap.timings_ms["detect"] = (time.monotonic() - t) * 1e3

    @staticmethod
    def _detect_failed(vcap: ViewCapture, recipe: RecipeConfig, cid: str, err: Exception) -> None:
        vcap.camera_errors[cid] = f"detection: {err}"
        vcap.refused.add(cid)
        vcap.detections[cid] = [
            MarkDetection.missing(m, f"detection: {err}")
            for m in sighted_marks(recipe, vcap.view, cid)
        ]

    # ------------------------------------------------------------------ measure + verdict
    def conclude(self, *, t0: float, recipe: ActiveRecipe,
                 views: Sequence[ViewCapture]) -> StationResult:
        """Measure from every view and gate: the station's verdict, ready to be recorded.

        The verdict is final here. What remains before a link has the answer (the record built
        and appended) is kept in reserve against the deadline: the recent slow (p90) append
        time, reported back by :meth:`note_append_ms`."""
        timings: dict[str, float] = {}
        for v in views:
            for stage, ms in v.timings_ms.items():
                key = stage if len(views) == 1 else f"v{v.view}_{stage}"
                timings[key] = timings.get(key, 0.0) + ms
        rc = recipe.config
        flange = {v.view: v.flange_pose for v in views if v.flange_pose is not None}
        meas: Measurement | None = None
        message = ""
        code: int
        obs: list[Observation] = []
        try:
            t = time.monotonic()
            obs = [o for v in views for o in v.observations()]
            cams = [vc for v in views for vc in v.cameras.values()]
            meas = measure(self.station, rc, obs, flange or None, self.options.estimate,
                           cameras=cams)
            timings["measure"] = (time.monotonic() - t) * 1e3
            if self.options.recorrect:
                t = time.monotonic()
                keys = [(v, cid) for v in views for cid in v.detections]
                groups = [(v.cameras[cid], v.detections[cid]) for v, cid in keys]
                corrs, shift = corrections_at(groups, rc, meas.T_rf_from_pf)
                if shift > self.options.recorrect_px:
                    moved = corrected(groups, corrs)
                    for (v, cid), dets in zip(keys, moved, strict=True):
                        v.detections[cid] = dets
                    obs = [o for v in views for o in v.observations()]
                    meas = measure(self.station, rc, obs, flange or None, self.options.estimate,
                                   initial_T_rf_from_pf=meas.T_rf_from_pf, cameras=cams)
                timings["correct"] = (time.monotonic() - t) * 1e3
            code, message = int(meas.gate.reason), meas.gate.message
        except PoseInputError as err:  # too few marks, a layout that fixes no pose, ...
            code, message = int(err.reason), str(err)
        except Exception as err:  # the record must still be written, with the reason
            log.exception("measurement failed")
            code, message = int(Reason.INTERNAL_ERROR), f"{type(err).__name__}: {err}"
        failed_cams = {cid for v in views for cid in v.camera_errors}
        if code in (Reason.MARKS_MISSING, Reason.TOO_FEW_MARKS) and failed_cams:
            errs = "; ".join(e for v in views for e in v.camera_errors.values())
            detect_only = all(set(v.camera_errors) <= v.refused for v in views)
            code = int(Reason.DETECTION_FAILED if detect_only else Reason.CAMERA_FAILED)
            message = f"{message}; {errs}"
        if code == 0 and meas is not None and not _finite_measurement(meas):
            code, message = int(Reason.INTERNAL_ERROR), "the estimate is not finite"
        if code == 0 and meas is not None:
            near, last = ((self._near[1], self._near[2])
                          if self._near is not None and self._near[0] is rc else (None, None))
            T = meas.T_rf_from_pf
            near = next_near(near, last, T, rc.T_rf_from_pf0.matrix, rc, self.options.detect)
            self._near = (rc, near, np.array(T, dtype=float))

        # Keep the usual slow append in reserve: the p90 of the last 50 without the slowest one.
        # Never the maximum: one fsync stall would otherwise fail the next triggers (with a few
        # appends known, their p90 is close to their maximum).
        reserve = max(self.options.store_reserve_ms, _usual_slow(self._store_ms))
        elapsed = (time.monotonic() - t0) * 1e3
        if code == 0 and elapsed + reserve > self.station.deadline_ms:
            code = int(Reason.DEADLINE_EXCEEDED)
            message = (f"the result was ready {elapsed:.1f} ms after the trigger and needs about "
                       f"{reserve:.1f} ms more to be stored: past the {self.station.deadline_ms:g}"
                       f" ms cycle deadline, so no offset is sent")
        frames = {(v.view, cid): img for v in views for cid, img in v.frames.items()}
        timings["total"] = (time.monotonic() - t0) * 1e3
        return StationResult(code=code, message=message, measurement=meas, views=tuple(views),
                             timings_ms=timings, frames=frames, observations=tuple(obs))

    def forget_last_part(self) -> None:
        """The next trigger's first windows at the reference, as if no part had been measured
        (``python -m bench displaced``: a part first seen where it sits)."""
        self._near = None

    def note_append_ms(self, ms: float) -> None:
        """How long the last record's append took (the deadline reserve learns from it)."""
        self._store_ms.append(ms)


def _usual_slow(values: Sequence[float]) -> float:
    """The 90th percentile (linear interpolation, as ``np.percentile``) of a few values without
    their largest, 0 for fewer than two: a single stall never counts. The standard library's
    ``statistics.quantiles`` takes ~10 µs for 50 values, ``np.percentile`` about a hundred."""
    rest = sorted(values)[:-1]
    if len(rest) < 2:  # quantiles needs two points (before Python 3.13)
        return float(rest[0]) if rest else 0.0
    return statistics.quantiles(rest, n=10, method="inclusive")[-1]


def _finite_measurement(meas: Measurement) -> bool:
    """Whether the offset and both sigmas are finite (on Python floats: eight numbers, for which
    numpy's isfinite would cost more than the check)."""
    values = [*np.asarray(meas.offset, dtype=float).ravel().tolist(),
              float(meas.sigma_trans_mm), float(meas.sigma_rot_deg)]
    return all(math.isfinite(v) for v in values)
