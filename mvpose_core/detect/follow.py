"""Small windows away from the prior: around the last part, or the pose of a displaced part's blobs.

When a part lies beyond the first reach (docs/detection.md, "Two reaches"), some of its marks
still leave blobs in their small windows (a mark near the rotation's centre moves little; a mark
at a window's edge is clipped but found). Their coarse centres (before measurement, within a few
pixels of the marks) give a pose by the refinement the measurement uses
(:func:`mvpose_core.refine.levenberg_marquardt`, started at the first windows' pose, with the
estimator's outlier rule; without its other starts and its covariance, which these windows do
not need: the same pose at ~40 % of the cost); the windows of the first reach around that pose
then hold the marks, and are searched instead of the whole tolerance's.

A pose is given only when it is trustworthy: three or more distinct marks, every kept blob within
:data:`AGREE_PX` of its projection at the pose, and the pose within the recipe's tolerance of the
prior. Otherwise ``None``: the caller searches the whole tolerance, as without this step.

Windows away from the prior (around that pose, or around the last good part's,
:func:`next_near`) keep the size and shape ranges of the whole tolerance's at the prior too
(:func:`held_predictions`): they never accept a blob that search would not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.detect.candidates import Candidate
from mvpose_core.detect.geometry import MarkPrediction, predict_marks_cached
from mvpose_core.detect.types import DetectOptions
from mvpose_core.problem import Observation, PoseInputError, build_problem
from mvpose_core.refine import LMResult, Packed, levenberg_marquardt
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

#: a blob farther than this from its mark's projection at the estimated pose (px) is dropped by
#: the estimator's outlier rule; a pose whose kept blobs are not all within it is not used
AGREE_PX = 12.0
_REJECTIONS = 2  # the most blobs dropped by the outlier rule
#: the last part's pose is remembered anew for the next trigger's windows only when it moved by
#: more than this share of the first reach (5 mm / 0.5° for 25 mm / 2.5°): the windows around
#: it are predicted once, and a part that close is far inside them
NEAR_SHARE = 0.2


def pose_from_blobs(
    blobs: Sequence[tuple[ViewCamera, list[MarkPrediction], list[tuple[int, Candidate]]]],
    recipe: RecipeConfig,
    T_prior: Array,
    start: Array | None = None,
) -> Array | None:
    """``T_rf_from_pf`` from each camera's blobs (index in its predictions, blob), or None.

    Each mark's blob nearest its prediction stands for it in that camera. The refinement
    starts at ``start`` (default: the prior); every mark in front of its camera, and the pose
    within the recipe's tolerance of the prior ``T_prior``.
    """
    obs: list[Observation] = []
    for cam, preds, cands in blobs:
        best: dict[int, tuple[float, Array]] = {}
        for k, c in cands:
            d = float(np.hypot(*(c.ellipse.centre - preds[k].uv)))
            if k not in best or d < best[k][0]:
                best[k] = (d, c.ellipse.centre)
        obs += [Observation(cam.view, cam.camera_id, preds[k].mark.mark_id, uv)
                for k, (_, uv) in best.items()]
    return pose_from_observations(obs, [c for c, _, _ in blobs], recipe, T_prior, start)


def pose_from_observations(
    obs: Sequence[Observation], cameras: Sequence[ViewCamera], recipe: RecipeConfig,
    T_prior: Array, start: Array | None = None,
) -> Array | None:
    """``T_rf_from_pf`` from image points of three or more distinct marks, or None: the
    refinement of :func:`pose_from_blobs` with its outlier rule and its checks."""
    if len({o.mark_id for o in obs}) < 3:
        return None
    marks_pf, _ = _marks_of(recipe)
    T_start = T_prior if start is None else start
    try:
        pk = build_problem(obs, list(cameras), marks_pf, 1.0).pk
        lm = _refine(pk, T_start[:3, :3], T_start[:3, 3])
        # The estimator's outlier rule: the blob farthest from its projection beyond AGREE_PX
        # is dropped and the pose refined again, never below three marks. The residuals and
        # depths are the refinement's own, of the blobs kept (at its converged step, moved to
        # first order: far below the pixel).
        rows = np.arange(len(obs))
        for n in range(_REJECTIONS + 1):
            length = np.hypot(lm.residuals[:, 0], lm.residuals[:, 1])
            worst = int(np.argmax(length))
            if length[worst] <= AGREE_PX or n == _REJECTIONS:
                break
            rows = np.delete(rows, worst)
            if len({obs[i].mark_id for i in rows.tolist()}) < 3:
                return None
            lm = _refine(pk.subset(rows), lm.R, lm.t)
    except (PoseInputError, np.linalg.LinAlgError):
        return None
    if not bool((lm.depth > 0).all()) or float(length[worst]) > AGREE_PX:
        return None
    T = np.eye(4)
    T[:3, :3] = lm.R
    T[:3, 3] = lm.t
    if not _within_tolerance(T, T_prior, recipe):
        return None
    return T


def _refine(pk: Packed, R: Array, t: Array) -> LMResult:
    return levenberg_marquardt(pk, R, t, max_iterations=10, step_tol=0.3)


def _predictions(cam: ViewCamera, recipe: RecipeConfig, T: Array, options: DetectOptions,
                 reach: float) -> list[MarkPrediction]:
    return predict_marks_cached(cam, recipe, T, options.size_tolerance, options.shape_slack_deg,
                                reach)


_HELD: IdentityCache[list[MarkPrediction]] = IdentityCache(32)


def held_predictions(cam: ViewCamera, recipe: RecipeConfig, T_prior: Array, T: Array,
                     options: DetectOptions, reach: float) -> list[MarkPrediction]:
    """The predictions at ``T`` (one per mark, in their order) with their size and shape ranges
    narrowed to the whole tolerance's at the prior; remembered like the predictions."""
    preds = _predictions(cam, recipe, T, options, reach)
    whole = _predictions(cam, recipe, T_prior, options, 1.0)

    def make() -> list[MarkPrediction]:
        w = {p.mark.mark_id: p for p in whole}
        out = []
        for p in preds:
            q = w[p.mark.mark_id]
            out.append(replace(
                p,
                radius_range=(max(p.radius_range[0], q.radius_range[0]),
                              min(p.radius_range[1], q.radius_range[1])),
                ratio_range=(max(p.ratio_range[0], q.ratio_range[0]),
                             min(p.ratio_range[1], q.ratio_range[1]))))
        return out

    return _HELD.get((cam, recipe, preds, whole), options, make)


def next_near(
    near: Array | None, last: Array | None, T: Array, T_prior: Array, recipe: RecipeConfig,
    options: DetectOptions,
) -> Array | None:
    """Where the next trigger's first windows go, after a part measured at ``T`` (the part
    before it was measured at ``last``; None: none, or not measured).

    A line whose parts sit off the reference at one place (a skid or fixture off its taught
    position) is searched there: once two parts in a row lay within the first reach of each
    other, the next trigger's first search is made in the first reach's windows around ``T``
    (``near``; None: the prior). A part that jumped from the last one says nothing about the
    next, so the search goes back to the prior, whose windows are remembered: a line whose parts
    scatter over the tolerance pays no window prediction at a pose it will not see again.
    ``near`` moves to ``T`` only when ``T`` is more than :data:`NEAR_SHARE` of the first reach
    away from it (so the windows around it are predicted once, not at every trigger), and goes
    back to None when ``T`` is that close to the prior. None when the recipe has one reach."""
    tol = recipe.tolerances
    if options.first_reach(tol.max_offset_mm, tol.max_offset_deg) is None:
        return None
    assert options.first_reach_mm is not None  # first_reach is None without it
    reach = (options.first_reach_mm, options.first_reach_deg)
    step = (NEAR_SHARE * reach[0], NEAR_SHARE * reach[1])
    if near is not None and _within(T, near, recipe, *step):
        return near
    if _within(T, T_prior, recipe, *step):
        return None
    if last is None or not _within(T, last, recipe, *reach):
        return None  # a part that jumped: the next search starts at the prior
    return np.array(T, dtype=float)


def _within_tolerance(T: Array, T_prior: Array, recipe: RecipeConfig) -> bool:
    """Whether ``T`` is within the recipe's tolerance of the prior."""
    tol = recipe.tolerances
    return _within(T, T_prior, recipe, tol.max_offset_mm, tol.max_offset_deg)


def _within(T: Array, T_ref: Array, recipe: RecipeConfig, mm: float, deg: float) -> bool:
    """Whether ``T`` is within ``mm`` / ``deg`` of ``T_ref`` (the marks' centroid moved no more
    than ``mm``, the rotation no more than ``deg``)."""
    # Both are rigid: the centroid c moved by |T c - T_ref c| (in either frame), and the
    # rotation between them has trace(R_refᵀ R) = Σ R_ref ∘ R. In closed form on floats: a 4x4
    # solve and its numpy calls cost ~0.1 ms on the trigger thread after detection.
    c = _marks_of(recipe)[1].tolist()
    a, b = T.tolist(), T_ref.tolist()
    moved = math.hypot(*(sum((a[i][j] - b[i][j]) * c[j] for j in range(3)) + a[i][3] - b[i][3]
                         for i in range(3)))
    trace = sum(a[i][j] * b[i][j] for i in range(3) for j in range(3))
    cos = min(1.0, max(-1.0, (trace - 1.0) / 2.0))
    return moved <= mm and math.degrees(math.acos(cos)) <= deg


_MARKS: IdentityCache[tuple[dict[str, Array], Array]] = IdentityCache(16)


def _marks_of(recipe: RecipeConfig) -> tuple[dict[str, Array], Array]:
    """The recipe's mark positions by id and their centroid (PF, mm), remembered per recipe
    (the blobs' pose and its checks run at every trigger of a part beyond the first reach);
    not to be changed."""

    def make() -> tuple[dict[str, Array], Array]:
        pf = {m.id: np.array(m.position, dtype=float) for m in recipe.marks}
        c = np.array(recipe.mark_centroid(), dtype=float)
        for a in (*pf.values(), c):
            a.flags.writeable = False
        return pf, c

    return _MARKS.get((recipe,), None, make)
