"""Per-camera reprojection residuals of one measurement, and how much of a camera's move they show.

A camera that moves (a knock, a loose mount, thermal creep) shifts every mark it sees by about the
same image vector. The pose estimate absorbs part of that shift — it moves the part a little to
fit the moved camera — and the rest stays in that camera's residuals. :func:`camera_residuals`
gives per (view, camera) the mean residual vector of one measurement, the input of the drift
watch (:mod:`mvpose_core.drift`); :func:`shift_response` measures, with the real estimator on a
noise-free scene, which part of a camera's image shift its mean residual keeps, so the drift
watch can report the camera's move rather than its visible part.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from mvpose_core.estimate import EstimateOptions, Observation, PoseResult
from mvpose_core.measure import measure
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import Array


@dataclass(frozen=True)
class CameraResidual:
    """One camera's residuals in one measurement (observed − predicted, distorted px)."""

    view: int
    camera_id: str
    mean_px: tuple[float, float]  # mean (du, dv) over the camera's observations
    rms_px: float  # √(mean |r|²) over the same observations
    count: int  # observations of this camera with a residual
    used: int  # of them in the fit (the rest left out by the robust rule, mvpose_core.robust)

    @property
    def key(self) -> tuple[int, str]:
        return (self.view, self.camera_id)


def camera_residuals(observations: Sequence[Observation], pose: PoseResult) -> list[CameraResidual]:
    """Mean residual vector, RMS and counts per (view, camera), sorted by view then camera.

    ``observations`` are the ones the pose was estimated from, in the same order (the rows of
    ``pose.residuals_px``, see :class:`mvpose_core.estimate.PoseResult`; only their view and
    camera are read, so the list given to :func:`mvpose_core.measure.measure` will do).
    Observations left out of the fit (``pose.used`` False) count too: a camera that moved by
    more than the robust rule's ``outlier_px`` is left out of the fit and shows its whole move
    in its residuals — the drift watch must see it (``used`` says how many were in the fit).
    """
    r = np.asarray(pose.residuals_px, dtype=float)
    if r.shape != (len(observations), 2):
        raise ValueError(
            f"pose.residuals_px has shape {r.shape}, expected ({len(observations)}, 2): "
            "pass the observations the pose was estimated from"
        )
    used = np.asarray(pose.used, dtype=bool)
    if used.shape != (len(observations),):  # a PoseResult built without ``used``: all in the fit
        used = np.ones(len(observations), dtype=bool)
    # On Python floats, summed in the observations' order: a few numbers per camera, for which
    # numpy's per-call cost (on the trigger thread, after detection) would be most of the work.
    rows: dict[tuple[int, str], list[tuple[float, float, bool]]] = {}
    for o, (du, dv), u in zip(observations, r.tolist(), used.tolist(), strict=True):
        if math.isfinite(du) and math.isfinite(dv):
            rows.setdefault((o.view, o.camera_id), []).append((du, dv, u))
    out = []
    for (view, cid), rs in sorted(rows.items()):
        su = sv = ss = 0.0
        for du, dv, _ in rs:
            su += du
            sv += dv
            ss += du * du + dv * dv
        n = len(rs)
        out.append(
            CameraResidual(
                view=view,
                camera_id=cid,
                mean_px=(su / n, sv / n),
                rms_px=math.sqrt(ss / n),
                count=n,
                used=sum(u for _, _, u in rs),
            )
        )
    return out


def shift_response(
    station: StationConfig,
    recipe: RecipeConfig,
    options: EstimateOptions = EstimateOptions(),  # noqa: B008 - frozen, immutable default
    *,
    step_px: float = 1.0,
) -> dict[tuple[int, str], dict[tuple[int, str], Array]]:
    """``response[moved][seen]``: 2x2 matrices with ``mean residual of seen ≈ A · shift of moved``.

    Measured with the real estimator at the recipe's taught pose, without noise and with every
    observation in the fit: each camera's observations in turn are shifted by ``step_px``
    along u, then along v, and every camera's mean residual is read (the linear response).
    ``response[c][c]`` is the identity for a camera the pose cannot move to fit and near zero
    for one whose shift the pose absorbs; the other cameras' blocks are the part of the shift
    the pose pushes into their residuals. :class:`mvpose_core.drift.DriftWatch` uses it to
    name the camera that moved and to estimate its move.
    """
    if not step_px > 0:
        raise ValueError(f"step_px must be > 0, got {step_px}")
    # The linear response of the fit: no observation left out (the watch blends in the
    # left-out case itself, DriftWatch.update's ``in_fit``).
    recipe = recipe.model_copy(
        update={
            "robust": recipe.robust.model_copy(update={"outlier_px": None, "stereo_check": False})
        }
    )
    T0 = recipe.T_rf_from_pf0.matrix
    clean = synthetic_observations(
        station, recipe, T0, np.random.default_rng(0), 0.0, require_in_image=False
    )
    base = {
        c.key: np.asarray(c.mean_px)
        for c in camera_residuals(clean, measure(station, recipe, clean, options=options).pose)
    }
    out: dict[tuple[int, str], dict[tuple[int, str], Array]] = {}
    for moved in sorted(base):
        cols: dict[tuple[int, str], Array] = {k: np.zeros((2, 2)) for k in base}
        for axis in (0, 1):
            d = np.zeros(2)
            d[axis] = step_px
            obs = [replace(o, uv=o.uv + d) if (o.view, o.camera_id) == moved else o for o in clean]
            for c in camera_residuals(obs, measure(station, recipe, obs, options=options).pose):
                cols[c.key][:, axis] = (np.asarray(c.mean_px) - base[c.key]) / step_px
        out[moved] = cols
    return out


@dataclass(frozen=True)
class TriggerResiduals:
    """One simulated trigger: per-camera mean residuals and in-fit fractions."""

    means_px: dict[tuple[int, str], tuple[float, float]]
    in_fit: dict[tuple[int, str], float]


def simulated_residuals(
    station: StationConfig,
    recipe: RecipeConfig,
    rng: np.random.Generator,
    n: int,
    *,
    shift_px: dict[tuple[int, str], tuple[float, float]] | None = None,
    max_mm: float = 5.0,
    max_deg: float = 0.5,
    sigma_px: float | None = None,
) -> list[TriggerResiduals]:
    """``n`` triggers measured by :func:`mvpose_core.measure.measure` on synthetic observations.

    Each trigger's part lies at a random displacement from the taught pose (uniform within
    ``max_mm`` / ``max_deg`` per axis), its observations carry N(0, σ²) noise (σ = the recipe's
    detector noise unless given), and each camera in ``shift_px`` has moved: every observation
    of that (view, camera) shifted by its (du, dv) px.
    """
    sigma = recipe.detector_noise_px if sigma_px is None else sigma_px
    T0 = recipe.T_rf_from_pf0.matrix
    out = []
    for _ in range(n):
        T = T0 @ random_displacement(rng, max_mm, max_deg)
        obs = synthetic_observations(station, recipe, T, rng, sigma)
        if shift_px:
            obs = [
                replace(o, uv=o.uv + np.asarray(shift_px[o.view, o.camera_id]))
                if (o.view, o.camera_id) in shift_px
                else o
                for o in obs
            ]
        cams = camera_residuals(obs, measure(station, recipe, obs).pose)
        out.append(
            TriggerResiduals(
                means_px={c.key: c.mean_px for c in cams},
                in_fit={c.key: c.used / c.count for c in cams},
            )
        )
    return out
