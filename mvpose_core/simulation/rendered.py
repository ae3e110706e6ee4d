"""Rendered-image studies of a whole station: render, detect, measure, and compare with the truth.

Each trial displaces the part about its marks' centroid (the displacement the recipe's
tolerances describe, see :func:`mvpose_core.detect.marks.displacement_mm`), renders every
camera of every view with :func:`mvpose_core.render.render_view` (per-camera options: a mark
hidden or a decoy painted in one camera only), detects the marks in windows predicted from the
taught pose, and measures with :func:`mvpose_core.measure.measure` (robust rule included).

The study's figures (:class:`RenderedStudy`):

- the detector's measured noise σ: RMS per axis of detected minus true centre over the
  observations the pose used;
- the Cramér–Rao bound at that σ: the estimator's covariance (computed at the recipe's
  ``detector_noise_px``) scaled by ``(σ / detector_noise_px)²``, at the grasp frame, per trial,
  its RMS over the trials;
- the pose's actual RMS error at the grasp frame (rotation in degrees, translation in mm) and its
  ratio to the bound.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from mvpose_core.detect import DetectOptions, detect_marks_many
from mvpose_core.estimate import Observation, PoseInputError
from mvpose_core.measure import Measurement, measure
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.robust import observations_of
from mvpose_core.scene import view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import Array, compose, invert, make_transform, transform_error
from mvpose_core.uncertainty import covariance_in_frame, sigma_figures


def displaced_about_marks(
    recipe: RecipeConfig, rng: np.random.Generator, max_mm: float, max_deg: float
) -> Array:
    """A random part pose ``T_rf_from_pf``: the taught pose moved by up to ``max_mm`` per axis
    and rotated by up to ``max_deg`` per axis about the marks' centroid."""
    T_pf_from_c = make_transform(np.eye(3), recipe.mark_centroid())
    D = random_displacement(rng, max_mm, max_deg)
    return compose(recipe.T_rf_from_pf0.matrix, T_pf_from_c, D, invert(T_pf_from_c))


@dataclass(frozen=True)
class RenderedTrial:
    """One trigger: the truth, the measurement (None if the estimator refused) and per used
    observation the detected minus true centre (px)."""

    T_true: Array
    measurement: Measurement | None
    refused: str | None
    errors_px: Array  # [N, 2] detected − true, observations used by the pose
    rot_err_deg: float  # at the grasp frame; nan when refused
    trans_err_mm: float


def rendered_trial(
    station: StationConfig,
    recipe: RecipeConfig,
    T_true: Array,
    rng: np.random.Generator,
    options: RenderOptions = RenderOptions(),  # noqa: B008 - frozen, immutable default
    per_camera: Mapping[str, RenderOptions] | None = None,
    detect: DetectOptions = DetectOptions(),  # noqa: B008 - frozen, immutable default
    measured_as: RecipeConfig | None = None,
) -> RenderedTrial:
    """Render every camera (``per_camera`` maps ``ViewCamera.key`` to its own options),
    detect, measure. ``measured_as`` is the recipe the detector and estimator are given (default
    ``recipe``, the one rendered): e.g. one with wrong diameters or the robust rule off."""
    seen = recipe if measured_as is None else measured_as
    cams = view_cameras(station)
    per_camera = per_camera or {}
    truth: dict[tuple[int, str, str], Array] = {}
    obs = []
    prior = recipe.T_rf_from_pf0.matrix
    for view in sorted({c.view for c in cams}):
        vcs = [c for c in cams if c.view == view]
        frames = []
        for vc in vcs:
            r = render_view(vc, recipe, T_true, rng, per_camera.get(vc.key, options))
            frames.append((r.image, vc))
            truth.update({(view, vc.camera_id, m): uv for m, uv in r.centres.items()})
        dets = detect_marks_many(frames, seen, prior, detect)
        obs += observations_of(view, {vc.camera_id: d for vc, d in zip(vcs, dets, strict=True)})
    try:
        m = measure(station, seen, obs, cameras=cams)
    except PoseInputError as err:
        return RenderedTrial(T_true, None, str(err), np.zeros((0, 2)), float("nan"),
                             float("nan"))
    errs = np.array([o.uv - truth[o.key] for o, u in zip(
        _final(m, obs), m.pose.used, strict=True) if u]).reshape(-1, 2)
    G = recipe.T_pf_from_grasp.matrix
    rot, trans = transform_error(compose(m.T_rf_from_pf, G), compose(T_true, G))
    return RenderedTrial(T_true, m, None, errs, rot, trans)


def _final(m: Measurement, obs: list[Observation]) -> list[Observation]:
    """The observations as the robust rule left them (replaced candidates put in)."""
    by_key = {(r.view, r.camera_id, r.mark_id): r.candidate for r in m.replaced}
    out = []
    for o in obs:
        k = by_key.get(o.key)
        out.append(o if not k else replace(o, uv=o.alternates[k - 1]))
    return out


@dataclass(frozen=True)
class RenderedStudy:
    """Figures of a series of rendered trials (see the module docstring)."""

    trials: int
    ok: int  # gate OK
    refused: int  # estimator refused (too few marks ...)
    sigma_px: float  # the detector's measured noise, per axis
    rms_rot_deg: float
    rms_trans_mm: float
    crb_rot_deg: float
    crb_trans_mm: float
    dropped: dict[str, int] = field(default_factory=dict)  # "v/cam/mark" -> times dropped
    reasons: dict[str, int] = field(default_factory=dict)  # gate reason name -> count

    @property
    def ratio_rot(self) -> float:
        return self.rms_rot_deg / self.crb_rot_deg

    @property
    def ratio_trans(self) -> float:
        return self.rms_trans_mm / self.crb_trans_mm

    def line(self, name: str) -> str:
        drop = ", ".join(f"{k} x{v}" for k, v in sorted(self.dropped.items())) or "none"
        return (
            f"{name}: {self.trials} trials, {self.ok} OK, {self.refused} refused; detector σ "
            f"{self.sigma_px:.4f} px; rotation RMS {self.rms_rot_deg:.5f}° vs bound "
            f"{self.crb_rot_deg:.5f}° ({self.ratio_rot:.2f}x); translation RMS "
            f"{self.rms_trans_mm:.4f} mm vs bound {self.crb_trans_mm:.4f} mm "
            f"({self.ratio_trans:.2f}x); dropped: {drop}"
        )


def rendered_study(
    station: StationConfig,
    recipe: RecipeConfig,
    trials: int,
    rng: np.random.Generator,
    max_mm: float = 5.0,
    max_deg: float = 0.5,
    options: RenderOptions = RenderOptions(),  # noqa: B008 - frozen, immutable default
    per_camera: Mapping[str, RenderOptions] | None = None,
    detect: DetectOptions = DetectOptions(),  # noqa: B008 - frozen, immutable default
    measured_as: RecipeConfig | None = None,
) -> RenderedStudy:
    """``trials`` rendered triggers with the part displaced about its marks' centroid."""
    runs = [
        rendered_trial(station, recipe, displaced_about_marks(recipe, rng, max_mm, max_deg), rng,
                       options, per_camera, detect, measured_as)
        for _ in range(trials)
    ]
    done = [r for r in runs if r.measurement is not None]
    errs = np.concatenate([r.errors_px for r in done]) if done else np.zeros((0, 2))
    sigma = float(np.sqrt(np.mean(errs**2))) if errs.size else float("nan")
    s0 = recipe.detector_noise_px
    G = recipe.T_pf_from_grasp.matrix
    bounds = np.array([
        sigma_figures(covariance_in_frame(r.measurement.pose.covariance, G) * (sigma / s0) ** 2)
        for r in done if r.measurement is not None
    ]).reshape(-1, 2)
    dropped: dict[str, int] = {}
    reasons: dict[str, int] = {}
    for r in done:
        assert r.measurement is not None
        for d in r.measurement.dropped:
            key = f"v{d.view}/{d.camera_id}/{d.mark_id}"
            dropped[key] = dropped.get(key, 0) + 1
        name = r.measurement.gate.reason.name
        reasons[name] = reasons.get(name, 0) + 1
    return RenderedStudy(
        trials=trials,
        ok=sum(1 for r in done if r.measurement is not None and r.measurement.gate.ok),
        refused=len(runs) - len(done),
        sigma_px=sigma,
        rms_rot_deg=_rms([r.rot_err_deg for r in done]),
        rms_trans_mm=_rms([r.trans_err_mm for r in done]),
        crb_rot_deg=_rms(bounds[:, 0].tolist()),
        crb_trans_mm=_rms(bounds[:, 1].tolist()),
        dropped=dropped,
        reasons=reasons,
    )


def _rms(x: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x else float("nan")
