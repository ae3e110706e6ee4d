"""The robust rule: a mark's observation that disagrees with the rest is replaced or dropped.

An observation is the detector's best candidate for a mark in one image; a decoy (a dot or hole
next to the mark) or a partly hidden mark gives one that the other observations contradict.
:func:`estimate_pose_robust` applies the recipe's rule (``RecipeConfig.robust``, on by default;
docs/engine.md):

1. **Stereo check** (``stereo_check``): within one view, a mark seen by two or more cameras must
   lie on its epipolar lines (within ``epipolar_px``). An observation that disagrees with every
   other camera's (both, for a pair) is *set aside* (unless more than ``max_dropped`` would be:
   then the images disagree as a whole, and none is). Which of a pair is right, and whether a
   next candidate is, the pose of the other marks decides (step 3): an epipolar line cannot
   (a blob anywhere along it agrees, and with a horizontal stereo pair that is a whole row).
2. The pose is estimated from the observations not set aside (all of them, if those alone do not
   determine a pose).
3. **Residual rule**, one change at a time, the pose re-estimated after each. Threshold τ: the
   larger of ``outlier_px``, five times the recipe's ``detector_noise_px`` and four times the
   median residual of the observations in use. When the largest residual of an observation in
   use exceeds ``outlier_px`` (or five σ), the pose is estimated without it; if its residual at
   that pose exceeds τ (of that pose), its next candidate closest to the prediction replaces it
   when within τ, else it is dropped (at most ``max_dropped``, never below three marks or a layout
   that no longer fixes the pose). If it is within τ, it does not stand out and nothing changes
   (uniformly poor images are the gate's to judge). Then an observation set aside or dropped
   whose best candidate now lies within τ is taken back.

What was replaced or dropped, and why, comes back with the pose; the quality gate then judges
what remains against the recipe's tolerances (so the result is OK when the rest suffices).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from mvpose_core.cache import IdentityCache
from mvpose_core.camera import CameraModel
from mvpose_core.detect.types import MarkDetection
from mvpose_core.estimate import EstimateOptions, PoseResult, SolveInfo, estimate_pose
from mvpose_core.problem import Observation, PoseInputError
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RobustConfig
from mvpose_core.transforms import Array, apply, compose, invert

Key = tuple[int, str, str]  # (view, camera_id, mark_id)


@dataclass(frozen=True)
class Dropped:
    """An observation the robust rule left out of the pose, and why."""

    view: int
    camera_id: str
    mark_id: str
    reason: str

    def as_dict(self) -> dict[str, object]:
        return {"view": self.view, "camera": self.camera_id, "mark": self.mark_id,
                "reason": self.reason}


@dataclass(frozen=True)
class Replaced:
    """An observation whose best candidate was replaced by its ``candidate``-th next one."""

    view: int
    camera_id: str
    mark_id: str
    candidate: int  # 1 = the first alternate
    reason: str

    def as_dict(self) -> dict[str, object]:
        return {"view": self.view, "camera": self.camera_id, "mark": self.mark_id,
                "candidate": self.candidate, "reason": self.reason}


@dataclass(frozen=True)
class RobustResult:
    """The pose over the kept observations and what the rule changed.

    ``observations`` are the ones given, with any replaced ``uv`` put in; ``pose.used`` says
    which of them the pose uses and ``pose.residuals_px`` holds every one's residual.
    """

    pose: PoseResult
    observations: tuple[Observation, ...]
    dropped: tuple[Dropped, ...]
    replaced: tuple[Replaced, ...]


def observations_of(
    view: int, detections: Mapping[str, Sequence[MarkDetection]]
) -> list[Observation]:
    """The found detections of one view (camera id → detections) as observations, each with
    its mark's next candidates."""
    return [
        Observation(view, cid, d.mark_id, d.uv, alternates=tuple(d.candidates()[1:]),
                    centre_variance=centre_variance(d.radius_px, d.fit_residual_px))
        for cid, dets in detections.items()
        for d in dets
        if d.found and d.uv is not None
    ]


def centre_variance(radius_px: float, fit_residual_px: float) -> float | None:
    """A found mark's relative centre variance, ``fit_residual_px² / radius_px``: the centre is
    the fit of the rim's edge points, whose scatter about the ellipse (the image noise over the
    edge's contrast, and whatever clutter or a partial occlusion adds) the fit's RMS residual
    measures, averaged over a rim of ∝ radius independent points. None when a figure is missing."""
    if not (np.isfinite(radius_px) and np.isfinite(fit_residual_px)
            and radius_px > 0 and fit_residual_px > 0):
        return None
    return float(fit_residual_px * fit_residual_px / radius_px)


def estimate_pose_robust(
    observations: Sequence[Observation],
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    config: RobustConfig = RobustConfig(),  # noqa: B008 - frozen, immutable default
    options: EstimateOptions = EstimateOptions(),  # noqa: B008 - frozen, immutable default
    sigma_px: float = 1.0,
    *,
    initial_T_rf_from_pf: np.ndarray | None = None,
    warm_start: np.ndarray | None = None,
) -> RobustResult:
    """:func:`mvpose_core.estimate.estimate_pose` under the robust rule (module docstring)."""
    obs = list(observations)
    n = len(obs)
    options = _rule_options(options, config.loss, config.huber_px)
    by_cam = {(c.view, c.camera_id): c for c in cameras}
    cands = [[o.uv, *o.alternates] for o in obs]
    every = _Candidates.of(cands)
    chosen = [0] * n
    why_out: dict[int, str] = {}  # set aside or dropped, with the reason
    replaced: dict[int, str] = {}
    if config.stereo_check:
        _stereo(obs, by_cam, config.epipolar_px, why_out)
        if len(why_out) > config.max_dropped:
            why_out.clear()  # the images disagree as a whole, not one mark: the gate judges
    used = np.array([k not in why_out for k in range(n)])

    def solve(mask: np.ndarray, start: Array | None) -> PoseResult:
        sub = [obs[k] if not chosen[k] else obs[k].but(uv=cands[k][chosen[k]])
               for k in np.asarray(mask).nonzero()[0].tolist()]
        return estimate_pose(sub, cameras, marks_pf, options, sigma_px,
                             initial_T_rf_from_pf=initial_T_rf_from_pf,
                             warm_start=start if start is not None else warm_start)

    try:
        pose = solve(used, None)
    except PoseInputError:
        if used.all():
            raise
        used[:] = True  # the stereo check left too little: let the residuals decide
        why_out.clear()
        pose = solve(used, None)
    # Five σ of the a-priori noise at least: a noisy station never loses good observations.
    limit = None if config.outlier_px is None else max(config.outlier_px, 5.0 * sigma_px)
    seen: tuple[PoseResult, Array] | None = None  # a pose and its predictions, once made
    if limit is not None:
        for _ in range(2 * n + 2):  # each pass makes one change; a few suffice in practice
            res, pred = _all_residuals(obs, cands, every, chosen, pose, used, by_cam, marks_pf)
            seen = (pose, pred)  # every change below comes with a new pose
            cur = np.array([res[k][chosen[k]] for k in range(n)])
            length = np.where(used, cur, -1.0)
            worst = int(np.argmax(length))
            if length[worst] > limit:
                # Judge the worst observation by the pose of the others: its own pull on the
                # pose hides part of its error, and it must stand out from theirs.
                trial = used.copy()
                trial[worst] = False
                try:
                    without = solve(trial, pose.T_rf_from_pf)
                except PoseInputError:
                    break  # the rest would not fix a pose: keep it, the gate judges
                res_w, _ = _all_residuals(obs, cands, every, chosen, without, trial, by_cam,
                                          marks_pf)
                tau = _threshold(limit, res_w, chosen, trial)
                best = int(np.argmin(res_w[worst])) if config.candidates else chosen[worst]
                if res_w[worst][chosen[worst]] <= tau:
                    break  # it does not stand out: the gate judges the residuals
                if res_w[worst][best] <= tau:
                    replaced[worst] = (f"residual {res_w[worst][chosen[worst]]:.2f} px > "
                                       f"{tau:.2f} px; candidate {best} fits "
                                       f"({res_w[worst][best]:.2f} px)")
                    chosen[worst] = best
                elif len(why_out) >= config.max_dropped:
                    break
                else:
                    why = f"residual {res_w[worst][chosen[worst]]:.2f} px > {tau:.2f} px"
                    if len(res_w[worst]) > 1:
                        why += f", no candidate within (best {min(res_w[worst]):.2f} px)"
                    used, pose = trial, without
                    why_out[worst] = why
                    continue
            else:
                tau = _threshold(limit, res, chosen, used)
                back = [k for k in range(n) if not used[k]
                        and (min(res[k]) if config.candidates else res[k][0]) <= tau]
                if not back:
                    break
                k = min(back, key=lambda j: min(res[j]))
                best = int(np.argmin(res[k])) if config.candidates else 0
                if best:
                    replaced[k] = f"{why_out[k]}; candidate {best} fits ({res[k][best]:.2f} px)"
                else:
                    replaced.pop(k, None)
                chosen[k] = best
                used[k] = True
                why_out.pop(k, None)
            pose = solve(used, pose.T_rf_from_pf)
    final = [o if not chosen[k] else o.but(uv=cands[k][chosen[k]]) for k, o in enumerate(obs)]
    pred = (seen[1] if seen is not None and seen[0] is pose
            else _predictions(final, cands, chosen, pose, used, by_cam, marks_pf))
    res_all = np.array([o.uv for o in final], dtype=float) - pred
    keys = [o.key for o in final]
    info = pose.info
    info = SolveInfo(
        info.iterations, info.initial_cost, info.final_cost, info.rms_px, info.termination,
        info.converged, info.initializer, tuple(keys[k] for k in sorted(why_out)),
    )
    in_objective = np.zeros(n, dtype=bool)  # left_only leaves right cameras out as well
    in_objective[used.nonzero()[0]] = pose.used
    full = PoseResult(pose.T_rf_from_pf, pose.covariance, res_all, info, in_objective)
    return RobustResult(
        full,
        tuple(final),
        tuple(Dropped(*keys[k], why_out[k]) for k in sorted(why_out)),
        tuple(Replaced(*keys[k], chosen[k], replaced[k]) for k in sorted(replaced)
              if chosen[k] and used[k]),
    )


@lru_cache(maxsize=16)
def _rule_options(options: EstimateOptions, loss: Literal["linear", "huber"],
                  huber_px: float) -> EstimateOptions:
    """The estimator's options under the rule's loss (made once: they are validated when made)."""
    return replace(options, loss=loss, huber_px=huber_px, outlier_px=None)


def _threshold(limit: float, res: list[Array], chosen: list[int], used: Array) -> float:
    """``limit``, or four times the median residual of the used observations if larger."""
    lengths = sorted(float(res[k][chosen[k]]) for k in used.nonzero()[0].tolist())
    if not lengths:
        return limit
    if any(x != x for x in lengths):  # a NaN: np.median's NaN, which max() passes over
        return limit
    m = len(lengths) // 2  # the median as np.median takes it: the middle one, or the mean of two
    median = lengths[m] if len(lengths) % 2 else (lengths[m - 1] + lengths[m]) / 2.0
    return max(limit, 4.0 * median)


def _predictions(
    obs: Sequence[Observation], cands: list[list[Array]], chosen: list[int], pose: PoseResult,
    mask: Array, by_cam: Mapping[tuple[int, str], ViewCamera], marks_pf: Mapping[str, np.ndarray],
) -> Array:
    """``["N", 2]`` where ``pose`` (estimated from the observations in ``mask``, with the
    candidates ``chosen``) puts each observation's mark: from the estimate's own residuals for
    those, one projection per camera for the rest (inf behind the camera)."""
    out = np.empty((len(obs), 2))
    idx = np.asarray(mask).nonzero()[0]
    out[idx] = np.array([cands[k][chosen[k]] for k in idx.tolist()], dtype=float).reshape(
        -1, 2) - pose.residuals_px
    rows: dict[tuple[int, str], list[int]] = {}
    for k in (~np.asarray(mask, dtype=bool)).nonzero()[0].tolist():
        rows.setdefault((obs[k].view, obs[k].camera_id), []).append(k)
    for key, ks in rows.items():
        cam = by_cam[key]
        P = np.array([marks_pf[obs[k].mark_id] for k in ks], dtype=float)
        p_cf = apply(compose(invert(cam.T_rf_from_cf), pose.T_rf_from_pf), P)
        ahead = p_cf[:, 2] > 0
        uv = cam.model.project(np.where(ahead[:, None], p_cf, [0.0, 0.0, 1.0]))
        out[ks] = np.where(ahead[:, None], uv, np.inf)
    return out


@dataclass(frozen=True)
class _Candidates:
    """Every observation's candidates in one array ``["K", 2]``: observation ``k``'s are rows
    ``bounds[k]:bounds[k + 1]``, and ``owner`` names each row's observation."""

    uv: Array
    owner: NDArray[np.intp]
    bounds: list[int]

    @classmethod
    def of(cls, cands: list[list[Array]]) -> _Candidates:
        counts = [len(cs) for cs in cands]
        uv = np.array([c for cs in cands for c in cs], dtype=float).reshape(-1, 2)
        owner = np.repeat(np.arange(len(cands)), counts)
        return cls(uv, owner, np.concatenate([[0], np.cumsum(counts)]).tolist())


def _all_residuals(
    obs: Sequence[Observation], cands: list[list[Array]], every: _Candidates, chosen: list[int],
    pose: PoseResult, mask: Array, by_cam: Mapping[tuple[int, str], ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
) -> tuple[list[Array], Array]:
    """Per observation, the residual length (px) of each of its candidates at ``pose``; and
    the :func:`_predictions` they come from."""
    pred = _predictions(obs, cands, chosen, pose, mask, by_cam, marks_pf)
    d = every.uv - pred[every.owner]
    length = np.sqrt(np.add.reduce(d * d, axis=1))  # what np.linalg.norm(axis=1) computes
    b = every.bounds
    return [length[b[k]:b[k + 1]] for k in range(len(cands))], pred


def _skew(t: Array) -> Array:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


#: the essential matrix of each camera pair (x_b^T E x_a = 0), for those very camera objects
_ESSENTIAL: IdentityCache[Array] = IdentityCache(64)


def _essential(ca: ViewCamera, cb: ViewCamera) -> Array:
    T_b_from_a = compose(invert(cb.T_rf_from_cf), ca.T_rf_from_cf)
    E = _skew(T_b_from_a[:3, 3]) @ T_b_from_a[:3, :3]
    E.flags.writeable = False
    return E


def _stereo(
    obs: Sequence[Observation], by_cam: Mapping[tuple[int, str], ViewCamera], limit: float,
    why_out: dict[int, str],
) -> None:
    """Step 1 of the rule: epipolar agreement between the cameras of a view, per mark; the
    observations that disagree with every other camera's are set aside in ``why_out``."""
    groups: dict[tuple[int, str], list[int]] = {}
    for k, o in enumerate(obs):
        groups.setdefault((o.view, o.mark_id), []).append(k)
    groups = {g: ks for g, ks in groups.items() if len(ks) > 1}
    if not groups:
        return
    # Every observation's normalised ray, one undistortion per camera; essential matrices per
    # camera pair.
    per_cam: dict[tuple[int, str], list[int]] = {}
    for ks in groups.values():
        for k in ks:
            per_cam.setdefault((obs[k].view, obs[k].camera_id), []).append(k)
    # One undistortion per lens (points are undistorted one by one: the same rays as per camera).
    per_lens: dict[CameraModel, list[int]] = {}  # equal models: the same lens
    for key, ks in per_cam.items():
        per_lens.setdefault(by_cam[key].model, []).extend(ks)
    rays: dict[int, Array] = {}
    for model, ks in per_lens.items():
        xy = model.undistort_normalized(np.array([obs[k].uv for k in ks], dtype=float))
        for k, x in zip(ks, xy, strict=True):
            rays[k] = np.array([x[0], x[1], 1.0])

    def dist(a: int, b: int) -> float:
        ca = by_cam[(obs[a].view, obs[a].camera_id)]
        cb = by_cam[(obs[b].view, obs[b].camera_id)]
        E = _ESSENTIAL.get((ca, cb), None, lambda: _essential(ca, cb))
        xa, xb = rays[a], rays[b]
        la, lb = E.T @ xb, E @ xa  # epipolar lines in a and in b (x_b^T E x_a = 0)
        da = abs(float(la @ xa)) / np.hypot(la[0], la[1]) * ca.model.fx
        db = abs(float(lb @ xb)) / np.hypot(lb[0], lb[1]) * cb.model.fx
        return 0.5 * (da + db)

    for ks in groups.values():
        d = {(a, b): dist(a, b) for a in ks for b in ks if a < b}
        for a in ks:
            others = [b for b in ks if b != a]
            if all(d[(min(a, b), max(a, b))] > limit for b in others):
                b = min(others, key=lambda j: d[(min(a, j), max(a, j))])
                why_out[a] = (f"epipolar {d[(min(a, b), max(a, b))]:.1f} px > {limit:g} px from "
                              f"v{obs[b].view}/{obs[b].camera_id}")
