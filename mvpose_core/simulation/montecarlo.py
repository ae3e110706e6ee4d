"""Monte Carlo runner: pose engine trials on synthetic scenes, split over processes, summarised.

Determinism: each point's random stream is ``SeedSequence(seed, spawn_key=point.seed_key)``,
spawned into fixed blocks of :data:`BLOCK` trials; a block's trials run in order from its own
generator. Which process runs a block does not change its numbers, so results depend on the
seed and the trial count only, never on the number of workers.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

import numpy as np

from mvpose_core.estimate import (
    EstimateOptions,
    Observation,
    PoseInputError,
    estimate_pose,
    pack_layout,
)
from mvpose_core.refine import project, residuals_and_jacobian
from mvpose_core.simulation.scenes import CAD_MARKS_4, Trial, build_trial, random_layout
from mvpose_core.simulation.studies import Scenario, StudyPoint
from mvpose_core.transforms import Array, transform_error
from mvpose_core.uncertainty import information_from_jacobian, invert_information

OBJECTIVES = ("all", "left_only")
_OPTIONS = {name: EstimateOptions(objective=name) for name in OBJECTIVES}  # type: ignore[arg-type]
#: per trial and objective: rotation error deg, translation error mm, bound variances deg², mm²
FIELDS = ("rot_deg", "trans_mm", "bound_rot_var", "bound_trans_var")
BLOCK = 25


def run_trial(scenario: Scenario, rng: np.random.Generator) -> Array:
    """One trial: ``[2 objectives, 4 FIELDS]``; NaN errors if the estimator fails or stalls."""
    marks = CAD_MARKS_4 if scenario.layout == "cad" else random_layout(scenario.n_marks, rng)
    trial = build_trial(
        marks,
        scenario.n_views,
        rng,
        scenario.motion,
        scenario.handeye.rot_deg,
        scenario.handeye.trans_mm,
    )
    T = trial.T_rf_from_pf
    pk, _ = pack_layout(trial.cameras_true, trial.marks_pf, trial.layout)
    uv, _ = project(pk, T[:3, :3], T[:3, 3])
    if scenario.sigma_px > 0:
        uv = uv + rng.normal(0.0, scenario.sigma_px, uv.shape)
    obs = [Observation(v, c, m, uv[i]) for i, (v, c, m) in enumerate(trial.layout)]
    # σ only weights the cost (equal for all rows): any positive value gives the same estimate.
    sigma = scenario.sigma_px if scenario.sigma_px > 0 else 1.0
    out = np.full((len(OBJECTIVES), len(FIELDS)), np.nan)
    for k, name in enumerate(OBJECTIVES):
        try:
            r = estimate_pose(obs, trial.cameras_believed, trial.marks_pf, _OPTIONS[name], sigma)
            if r.info.converged:
                out[k, :2] = transform_error(r.T_rf_from_pf, T)
        except PoseInputError:
            pass
    out[:, 2:] = _bounds(trial, scenario.sigma_px)
    return out


def _bounds(trial: Trial, sigma_px: float) -> Array:
    """Cramér–Rao variances (deg², mm²) of both objectives at the truth, from one Jacobian."""
    T = trial.T_rf_from_pf
    pk, _ = pack_layout(trial.cameras_believed, trial.marks_pf, trial.layout)
    _, J, _ = residuals_and_jacobian(pk, T[:3, :3], T[:3, 3])
    left = np.array([c.rig_position == 0 for c in trial.cameras_believed])
    index = {(c.view, c.camera_id): i for i, c in enumerate(trial.cameras_believed)}
    rows = {
        "all": np.ones(len(trial.layout), dtype=bool),
        "left_only": np.array([left[index[(v, c)]] for v, c, _ in trial.layout]),
    }
    out = np.full((len(OBJECTIVES), 2), np.nan)
    for k, name in enumerate(OBJECTIVES):
        try:
            cov = invert_information(information_from_jacobian(J[rows[name]]))  # at σ = 1 px
        except ValueError:
            continue
        out[k] = (
            math.degrees(1.0) ** 2 * float(np.trace(cov[:3, :3])),
            float(np.trace(cov[3:, 3:])),
        )
    return out * sigma_px**2  # the bound scales with σ² (zero without noise)


def run_block(task: tuple[Scenario, np.random.SeedSequence, int]) -> Array:
    """``n`` trials of one scenario from one seed: ``[n, 2, 4]`` (module-level so it pickles)."""
    scenario, seed, n = task
    rng = np.random.default_rng(seed)
    return np.stack([run_trial(scenario, rng) for _ in range(n)])


def _tasks(
    point: StudyPoint, trials: int, seed: int
) -> list[tuple[Scenario, np.random.SeedSequence, int]]:
    ss = np.random.SeedSequence(seed, spawn_key=point.seed_key)
    sizes = [min(BLOCK, trials - b) for b in range(0, trials, BLOCK)]
    return [(point.scenario, s, n) for s, n in zip(ss.spawn(len(sizes)), sizes, strict=True)]


def run_points(
    points: Sequence[StudyPoint],
    trials: int,
    seed: int,
    workers: int = 2,
    progress: Callable[[int], None] | None = None,
) -> list[Array]:
    """Samples ``[trials, 2, 4]`` per point; ``progress(n)`` after every n trials done.

    ``workers`` ≤ 1 runs in this process (no pool); otherwise a ProcessPoolExecutor.
    """
    if trials < 1:
        raise ValueError(f"trials must be ≥ 1, got {trials}")
    if seed < 0:
        raise ValueError(f"seed must be ≥ 0, got {seed}")
    tasks: list[tuple[Scenario, np.random.SeedSequence, int]] = []
    owner: list[int] = []
    for i, p in enumerate(points):
        t = _tasks(p, trials, seed)
        tasks.extend(t)
        owner.extend([i] * len(t))
    parts: list[list[Array]] = [[] for _ in points]

    def collect(results: Iterable[Array]) -> None:
        for i, block in zip(owner, results, strict=True):
            parts[i].append(block)
            if progress is not None:
                progress(block.shape[0])

    if workers <= 1:
        collect(run_block(t) for t in tasks)
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            # map keeps the task order, so every point's blocks are joined in seed order.
            collect(pool.map(run_block, tasks, chunksize=1))
    return [np.concatenate(p) for p in parts]


@dataclass(frozen=True)
class PointSummary:
    """Statistics of one point and objective (deg, mm; errors of the part origin)."""

    study: str
    series: str
    x: float
    objective: str  # "all" (both cameras of each view) | "left_only" (the paper's eq. 15)
    trials: int
    failed: int  # no pose or not converged: left out of the statistics
    rot_mean: float
    rot_rms: float
    rot_std: float
    trans_mean: float
    trans_rms: float
    trans_std: float
    bound_rot: float  # Cramér–Rao bound on the RMS error (pixel noise only)
    bound_trans: float


def summarise(point: StudyPoint, samples: Array) -> list[PointSummary]:
    """One :class:`PointSummary` per objective from ``[trials, 2, 4]`` samples."""
    out = []
    for k, name in enumerate(OBJECTIVES):
        s = samples[:, k, :]
        ok = np.isfinite(s[:, 0]) & np.isfinite(s[:, 1])
        rot, trans = s[ok, 0], s[ok, 1]

        def stats(e: Array) -> tuple[float, float, float]:
            if e.size == 0:
                return (math.nan,) * 3
            return (
                float(e.mean()),
                float(np.sqrt(np.mean(e * e))),
                float(e.std(ddof=1) if e.size > 1 else 0.0),
            )

        bound = (
            np.sqrt(np.nanmean(s[:, 2:], axis=0))
            if np.isfinite(s[:, 2:]).any()
            else (math.nan,) * 2
        )
        out.append(
            PointSummary(
                point.study,
                point.series,
                point.x,
                name,
                int(s.shape[0]),
                int((~ok).sum()),
                *stats(rot),
                *stats(trans),
                float(bound[0]),
                float(bound[1]),
            )
        )
    return out
