"""Station planning: predict a station's accuracy at a recipe's grasp point before it is built.

For a station description and a recipe: the Cramér–Rao bound at the grasp point (both cameras of
each rig, and the paper's left-camera objective), a Monte Carlo of the real estimator on
synthetic observations of the part displaced around its taught pose, whether both meet the
recipe's tolerances, and what losing one mark or one camera would cost (worst first).

Figures are 1σ RMS magnitudes at the grasp frame (√trace of each 3x3 block, as the quality gate
uses them): rotation in degrees, translation in millimetres.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mvpose_core.estimate import EstimateOptions, PoseInputError, estimate_pose
from mvpose_core.initial import COLLINEAR_RATIO, collinearity
from mvpose_core.scene import ViewCamera, project_recipe_marks, sighted_marks, view_cameras
from mvpose_core.simulation.scenes import rig_errors
from mvpose_core.simulation.studies import HANDEYE_LEVELS, HandEyeLevel
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import Array, compose, transform_error
from mvpose_core.uncertainty import (
    LayoutEntry,
    covariance_in_frame,
    cramer_rao_covariance,
    sigma_figures,
)

#: how far the simulated part lies off its taught pose (uniform per axis)
PLAN_DISPLACEMENT_MM = 5.0
PLAN_DISPLACEMENT_DEG = 0.5


class PlanningError(ValueError):
    """The station cannot measure this recipe (pose not determined) or the request is invalid."""


@dataclass(frozen=True)
class Accuracy:
    """1σ RMS rotation (deg) and translation (mm) at the grasp point."""

    rot_deg: float
    trans_mm: float

    def within(self, tolerance: Accuracy) -> bool:
        return self.rot_deg <= tolerance.rot_deg and self.trans_mm <= tolerance.trans_mm

    def load(self, tolerance: Accuracy) -> float:
        """The larger of the two figures as a fraction of its tolerance (1 = at the limit)."""
        return max(self.rot_deg / tolerance.rot_deg, self.trans_mm / tolerance.trans_mm)


@dataclass(frozen=True)
class LossImpact:
    """The grasp-point bound when one mark or one camera is lost (None: pose undetermined)."""

    kind: Literal["mark", "camera"]
    name: str
    bound: Accuracy | None


@dataclass(frozen=True)
class StationPlan:
    station: str
    recipe: str
    sigma_px: float
    robot_mounted: bool
    observations: int
    marks: tuple[str, ...]
    cameras: tuple[str, ...]
    bound: Accuracy  # Cramér–Rao, both cameras of each rig
    bound_left_only: (
        Accuracy | None
    )  # the paper's objective; None: fixed cameras only, or undetermined
    monte_carlo: Accuracy | None  # RMS error of the estimator over the trials that converged
    trials: int
    failed: int
    tolerance: Accuracy
    handeye: HandEyeLevel  # flange pose error in the Monte Carlo
    losses: tuple[LossImpact, ...]  # worst first
    warnings: tuple[str, ...]

    @property
    def meets_tolerances(self) -> bool:
        mc_ok = self.monte_carlo is not None and self.monte_carlo.within(self.tolerance)
        return self.bound.within(self.tolerance) and mc_ok and self.failed == 0


def recipe_layout(
    station: StationConfig, recipe: RecipeConfig
) -> tuple[list[ViewCamera], list[LayoutEntry]]:
    """The station's view cameras and every (view, camera, mark) the recipe expects to see."""
    cameras = view_cameras(station)
    layout = [
        (c.view, c.camera_id, m)
        for c in cameras
        for m in sighted_marks(recipe, c.view, c.camera_id)
    ]
    return cameras, layout


def grasp_bound(
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, Array],
    layout: Sequence[LayoutEntry],
    T_rf_from_pf: Array,
    T_pf_from_grasp: Array,
    sigma_px: float,
    objective: Literal["all", "left_only"] = "all",
) -> Accuracy:
    """Cramér–Rao 1σ at the grasp frame; :class:`PlanningError` if the pose is not determined."""
    kept = [e for e in layout if objective == "all" or _is_left(cameras, e)]
    ids = sorted({m for _, _, m in kept})
    if len(ids) < 3:
        raise PlanningError(
            f"pose not determined: {len(ids)} distinct marks seen {ids}, need at least 3"
        )
    if collinearity(np.array([marks_pf[m] for m in ids])) < COLLINEAR_RATIO:
        raise PlanningError(f"pose not determined: marks {ids} are collinear")
    try:
        cov = cramer_rao_covariance(cameras, marks_pf, layout, T_rf_from_pf, sigma_px, objective)
    except ValueError as err:
        raise PlanningError(f"pose not determined: {err}") from None
    return Accuracy(*sigma_figures(covariance_in_frame(cov, T_pf_from_grasp)))


def _is_left(cameras: Sequence[ViewCamera], entry: LayoutEntry) -> bool:
    return any(
        c.view == entry[0] and c.camera_id == entry[1] and c.rig_position == 0 for c in cameras
    )


def plan_station(
    station: StationConfig,
    recipe: RecipeConfig,
    rng: np.random.Generator,
    sigma_px: float | None = None,
    trials: int = 2000,
    progress: Callable[[int], None] | None = None,
    handeye: HandEyeLevel = HANDEYE_LEVELS["zero"],
) -> StationPlan:
    """Predict ``recipe``'s accuracy on ``station`` (σ defaults to the recipe's detector noise).

    ``handeye`` adds, in the Monte Carlo only, an independent error of each robot view's flange
    pose relative to the first view (as in the views study); the bound stays pixel-noise only.
    """
    sigma = recipe.detector_noise_px if sigma_px is None else float(sigma_px)
    if not (np.isfinite(sigma) and sigma > 0):
        raise PlanningError(f"detector noise must be a positive number of pixels, got {sigma_px}")
    if trials < 1:
        raise PlanningError(f"trials must be ≥ 1, got {trials}")
    if (handeye.rot_deg > 0 or handeye.trans_mm > 0) and not station.robot_mounted:
        raise PlanningError(
            f"station {station.name!r} has no robot-mounted rig: hand-eye level "
            f"{handeye.name!r} does not apply"
        )
    cameras, layout = recipe_layout(station, recipe)
    marks = {m.id: np.asarray(m.position, dtype=float) for m in recipe.marks}
    T0 = recipe.T_rf_from_pf0.matrix
    G = recipe.T_pf_from_grasp.matrix
    try:
        bound = grasp_bound(cameras, marks, layout, T0, G, sigma)
    except PlanningError as err:
        raise PlanningError(f"station {station.name!r}, recipe {recipe.name!r}: {err}") from None
    left: Accuracy | None = None
    if station.robot_mounted:  # the paper's objective is about a stereo rig on the robot
        try:
            left = grasp_bound(cameras, marks, layout, T0, G, sigma, "left_only")
        except PlanningError:
            left = None
    tol = Accuracy(recipe.tolerances.rotation_deg, recipe.tolerances.translation_mm)

    losses: list[LossImpact] = []
    for kind, names, index in (
        ("mark", sorted({e[2] for e in layout}), 2),
        ("camera", sorted({e[1] for e in layout}), 1),
    ):
        for name in names:
            rest = [e for e in layout if e[index] != name]
            try:
                b: Accuracy | None = grasp_bound(cameras, marks, rest, T0, G, sigma)
            except PlanningError:
                b = None
            losses.append(LossImpact(kind, name, b))  # type: ignore[arg-type]
    losses.sort(key=lambda x: -np.inf if x.bound is None else -x.bound.load(tol))

    errors, failed = _monte_carlo(
        station, recipe, cameras, marks, rng, sigma, trials, progress, handeye
    )
    mc = Accuracy(*map(float, np.sqrt(np.mean(errors**2, axis=0)))) if len(errors) else None
    return StationPlan(
        station=station.name,
        recipe=recipe.name,
        sigma_px=sigma,
        robot_mounted=station.robot_mounted,
        observations=len(layout),
        marks=tuple(sorted({e[2] for e in layout})),
        cameras=tuple(sorted({e[1] for e in layout})),
        bound=bound,
        bound_left_only=left,
        monte_carlo=mc,
        trials=trials,
        failed=failed,
        tolerance=tol,
        handeye=handeye,
        losses=tuple(losses),
        warnings=tuple(_outside_image(cameras, recipe, T0)),
    )


def _monte_carlo(
    station: StationConfig,
    recipe: RecipeConfig,
    cameras: list[ViewCamera],
    marks: dict[str, Array],
    rng: np.random.Generator,
    sigma: float,
    trials: int,
    progress: Callable[[int], None] | None,
    handeye: HandEyeLevel,
) -> tuple[Array, int]:
    T0 = recipe.T_rf_from_pf0.matrix
    G = recipe.T_pf_from_grasp.matrix
    errors = []
    failed = 0
    for i in range(trials):
        T = compose(T0, random_displacement(rng, PLAN_DISPLACEMENT_MM, PLAN_DISPLACEMENT_DEG))
        flanges = _flange_errors(station, rng, handeye)
        obs = synthetic_observations(
            station, recipe, T, rng, sigma, flanges, require_in_image=False
        )
        try:
            r = estimate_pose(
                obs, cameras, marks, EstimateOptions(), sigma, initial_T_rf_from_pf=T0
            )
        except PoseInputError:
            r = None
        if r is None or not r.info.converged:
            failed += 1
        else:
            errors.append(transform_error(compose(r.T_rf_from_pf, G), compose(T, G)))
        if progress is not None and (i + 1) % 100 == 0:
            progress(100)
    if progress is not None and trials % 100:
        progress(trials % 100)
    return np.array(errors).reshape(-1, 2), failed


def _flange_errors(
    station: StationConfig, rng: np.random.Generator, level: HandEyeLevel
) -> dict[int, Array] | None:
    """True flange poses of the robot views after the first, each off by its own random error."""
    if level.rot_deg == 0 and level.trans_mm == 0:
        return None
    views = [v for v in station.views if v.T_rf_from_gf is not None]
    err = rig_errors(rng, len(views), level.rot_deg, level.trans_mm)
    return {v.id: v.T_rf_from_gf.matrix @ err[i] for i, v in enumerate(views) if i > 0}  # type: ignore[union-attr]


def _outside_image(cameras: Sequence[ViewCamera], recipe: RecipeConfig, T0: Array) -> list[str]:
    out = []
    for cam in cameras:
        for pm in project_recipe_marks(cam, recipe, T0):
            if pm.depth_mm <= 0:
                out.append(f"mark {pm.mark_id} is behind camera {cam.key} at the taught pose")
            elif not cam.model.in_image(pm.uv[None])[0]:
                out.append(
                    f"mark {pm.mark_id} falls outside camera {cam.key} at the taught pose "
                    f"({pm.uv[0]:.0f}, {pm.uv[1]:.0f}) px"
                )
    return out
