"""Multi-view 6-DoF pose of a part from mark observations in every camera of every view.

``estimate_pose`` works in the robot base frame RF (every camera posed in RF by
:mod:`mvpose_core.scene`) and returns ``T_rf_from_pf``. Steps:

1. validate the input at this edge (shapes, NaN, unknown cameras/marks, duplicates, too few or
   collinear marks; :mod:`mvpose_core.problem`) — :class:`PoseInputError` names the problem;
2. start: 3D alignment to marks triangulated from two or more rays, else a generalised-camera
   DLT on single rays, else the caller's prior (``initial_T_rf_from_pf``) — see
   :mod:`mvpose_core.initial`;
3. refine: Levenberg–Marquardt on the reprojection error of every observation in every camera
   (the paper's eq. 15 over both cameras of each rig), or the paper's left-camera-only objective;
   optional Huber loss and outlier rejection (rule in :class:`EstimateOptions`);
4. covariance from the final Jacobian (the refinement's own JᵀWJ when it saw every observation;
   parametrisation in :mod:`mvpose_core.uncertainty`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mvpose_core.initial import COLLINEAR_RATIO, align_points, collinearity, generalized_dlt
from mvpose_core.problem import Observation, PoseInputError, Problem, build_problem, pack_layout
from mvpose_core.reasons import Reason
from mvpose_core.refine import Array, LMResult, Packed, levenberg_marquardt, residuals_and_jacobian
from mvpose_core.scene import ViewCamera
from mvpose_core.transforms import check_transform, make_transform
from mvpose_core.triangulate import rays_intersection
from mvpose_core.uncertainty import information_from_jacobian, invert_information

# Observation, PoseInputError and pack_layout live in mvpose_core.problem; import them from here.
__all__ = [
    "EstimateOptions", "Observation", "PoseInputError", "PoseResult", "SolveInfo",
    "estimate_pose", "pack_layout",
]  # fmt: skip


@dataclass(frozen=True)
class EstimateOptions:
    """Solver options (frozen; defaults suit the stations in deploy/).

    Outlier rule (``outlier_px`` set): after convergence, the observation with the largest
    residual length is dropped if that length exceeds ``outlier_px``, and the pose is refined
    again; repeated until every residual is within ``outlier_px``, but never below three marks
    or a layout that no longer determines the pose (then the gate judges the residuals).
    """

    objective: Literal["all", "left_only"] = (
        "all"  # left_only = paper eq. 15: first camera of each rig
    )
    loss: Literal["linear", "huber"] = "linear"
    huber_px: float = 2.0
    outlier_px: float | None = None
    max_iterations: int = 50
    max_rejections: int = 3
    #: a start whose refined RMS exceeds this (px) makes the solver try the next start
    restart_rms_px: float = 20.0
    #: converged when a step is shorter than this many σ of the estimate (see
    #: refine.levenberg_marquardt; the last step is still applied from the linear model, so
    #: the pose ends within ~1e-4 σ of full convergence: tests/mvpose_core/test_estimate.py)
    step_tol: float = 3e-2
    cost_tol: float = 1e-12

    def __post_init__(self) -> None:
        if self.objective not in ("all", "left_only"):
            raise ValueError(f"objective must be 'all' or 'left_only', got {self.objective!r}")
        if self.loss not in ("linear", "huber"):
            raise ValueError(f"loss must be 'linear' or 'huber', got {self.loss!r}")
        if not self.huber_px > 0:
            raise ValueError(f"huber_px must be > 0, got {self.huber_px}")
        if self.outlier_px is not None and not self.outlier_px > 0:
            raise ValueError(f"outlier_px must be > 0 or None, got {self.outlier_px}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be ≥ 1, got {self.max_iterations}")


@dataclass(frozen=True)
class SolveInfo:
    """How the solve went (PoseLib-style statistics)."""

    iterations: int
    initial_cost: float  # Σ ρ(|r|)/σ² at the start (½ Σ |r/σ|² for the linear loss)
    final_cost: float
    rms_px: float  # √(mean |r|²) over the observations used, px (OpenCV's RMS)
    termination: str  # "step" | "cost" | "no_decrease" | "max_iterations"
    converged: bool
    initializer: str  # "warm_start" | "triangulation" | "generalized_dlt" | "prior"
    rejected: tuple[tuple[int, str, str], ...] = ()  # (view, camera_id, mark_id) dropped


@dataclass(frozen=True)
class PoseResult:
    """The part pose in RF with its covariance and per-observation residuals.

    ``covariance`` is 6x6 over δ = (ω [rad], v [mm]), the right perturbation
    ``T_true = T_rf_from_pf · Exp(δ)`` in the part frame, from the Jacobian and the detector σ.
    ``residuals_px`` is observed − predicted, ``[N, 2]``, in the order of the observations
    (rejected and, for ``left_only``, right-camera observations included).
    """

    T_rf_from_pf: np.ndarray
    covariance: np.ndarray
    residuals_px: np.ndarray
    info: SolveInfo
    used: np.ndarray = field(
        default_factory=lambda: np.zeros(0, dtype=bool)
    )  # [N] in the objective


# ----------------------------------------------------------------------------- estimation


def estimate_pose(
    observations: Sequence[Observation],
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    options: EstimateOptions = EstimateOptions(),  # noqa: B008 - frozen, immutable default
    sigma_px: float = 1.0,
    *,
    initial_T_rf_from_pf: np.ndarray | None = None,
    warm_start: np.ndarray | None = None,
) -> PoseResult:
    """Estimate ``T_rf_from_pf`` from mark observations (see the module docstring).

    ``initial_T_rf_from_pf`` is a prior (e.g. the taught pose) used only when the layout gives
    no start of its own; ``warm_start`` (e.g. the pose of the same part a moment ago) is tried
    before the layout's starts. Either is kept only if its refined RMS is within
    ``options.restart_rms_px``, otherwise the next start is tried.
    """
    prob = build_problem(observations, cameras, marks_pf, sigma_px)
    pk_all, mi = prob.pk, prob.mi
    n = len(observations)
    # "all": build_problem has checked that the observations hold three distinct marks.
    objective = np.ones(n, dtype=bool) if options.objective == "all" else prob.table.left[prob.ci]
    if options.objective != "all" and len(set(mi[objective].tolist())) < 3:
        raise PoseInputError(
            f"too few marks for the {options.objective} objective: "
            f"{sorted({prob.mark_ids[j] for j in mi[objective]})}",
            Reason.TOO_FEW_MARKS,
        )

    starts = _starts(prob, cameras, initial_T_rf_from_pf)
    if warm_start is not None:
        T_warm = check_transform(warm_start, "warm_start")
        starts.insert(0, ("warm_start", lambda: (T_warm[:3, :3].copy(), T_warm[:3, 3].copy())))
    active = objective.copy()
    best: tuple[LMResult, str] | None = None
    best_in_front = False
    iterations = 0
    for name, make in starts:
        start = make()
        if start is None:
            continue
        pk = pk_all if active.all() else pk_all.subset(active)
        lm = _refine(pk, start, options)
        iterations += lm.iterations
        # A mirrored minimum with marks behind the cameras can fit well: rank it last.
        in_front = bool((lm.depth > 0).all())
        if best is None or (in_front, -lm.final_cost) > (best_in_front, -best[0].final_cost):
            best, best_in_front = (lm, name), in_front
        if in_front and _rms(lm) <= options.restart_rms_px:
            break
    if best is None:
        raise PoseInputError(
            "no start for the pose: need 3 non-collinear marks each seen by two cameras, or 6 "
            "single observations in general position, or a prior pose",
            Reason.POSE_NOT_DETERMINED,
        )
    lm, initializer = best
    initial_cost = lm.initial_cost

    rejected: list[tuple[int, str, str]] = []
    if options.outlier_px is not None:
        while len(rejected) < options.max_rejections:
            res, _, _ = residuals_and_jacobian(pk_all, lm.R, lm.t)
            length = np.where(active, np.linalg.norm(res, axis=1), -1.0)
            worst = int(np.argmax(length))
            if length[worst] <= options.outlier_px:
                break
            trial = active.copy()
            trial[worst] = False
            if len(set(mi[trial].tolist())) < 3:
                break
            try:
                invert_information(
                    information_from_jacobian(
                        residuals_and_jacobian(pk_all.subset(trial), lm.R, lm.t)[1]
                    )
                )
            except ValueError:
                break
            active = trial
            rejected.append(prob.keys[worst])
            lm = _refine(pk_all.subset(active), (lm.R, lm.t), options)
            iterations += lm.iterations

    all_used = bool(active.all())
    if all_used:  # the last refinement saw every observation
        res, J, depth = lm.residuals, lm.jacobian, lm.depth
    else:
        res, J, depth = residuals_and_jacobian(pk_all, lm.R, lm.t)
    behind = np.flatnonzero(~(depth > 0))
    if behind.size:
        o = observations[int(behind[0])]
        raise PoseInputError(
            f"mark {o.mark_id!r} would be behind camera v{o.view}/{o.camera_id} "
            f"(depth {depth[behind[0]]:.1f} mm): wrong camera, mark or camera pose",
            Reason.MARK_BEHIND_CAMERA,
        )
    try:
        if all_used and lm.information is not None:  # the refinement's own, at J's pose
            cov = invert_information(lm.information)
        else:
            Jw = J[active] * pk_all.weight[active][:, None, None]
            cov = invert_information(information_from_jacobian(Jw))
    except ValueError as err:
        raise PoseInputError(str(err), Reason.POSE_NOT_DETERMINED) from None
    r_act = res if all_used else res[active]
    info = SolveInfo(
        iterations=iterations,
        initial_cost=initial_cost,
        final_cost=lm.final_cost,
        rms_px=float(np.sqrt(np.einsum("ni,ni->", r_act, r_act) / r_act.shape[0])),
        termination=lm.termination,
        converged=lm.converged,
        initializer=initializer,
        rejected=tuple(rejected),
    )
    return PoseResult(make_transform(lm.R, lm.t), cov, res, info, active)


def _refine(pk: Packed, start: tuple[Array, Array], options: EstimateOptions) -> LMResult:
    return levenberg_marquardt(
        pk,
        start[0],
        start[1],
        loss=options.loss,
        huber_px=options.huber_px,
        max_iterations=options.max_iterations,
        step_tol=options.step_tol,
        cost_tol=options.cost_tol,
    )


def _rms(lm: LMResult) -> float:
    r = lm.residuals
    return float(np.sqrt(np.einsum("ni,ni->", r, r) / r.shape[0]))


Start = Callable[[], "tuple[Array, Array] | None"]


def _starts(
    prob: Problem, cameras: Sequence[ViewCamera], prior: np.ndarray | None
) -> list[tuple[str, Start]]:
    """Candidate starts in order of preference, each computed only when asked for."""
    rays: dict[str, tuple[Array, Array]] = {}

    def get_rays() -> tuple[Array, Array]:
        if not rays:
            pk, ci = prob.pk, prob.ci
            if prob.table.lens is not None:
                # One lens model for the whole station (the usual case): one undistortion call.
                xy = cameras[int(ci[0])].model.undistort_normalized(pk.uv)
            else:
                xy = np.empty_like(pk.uv)
                for c in np.unique(ci).tolist():
                    rows = ci == c
                    xy[rows] = cameras[c].model.undistort_normalized(pk.uv[rows])
            ray = np.empty((len(ci), 3))
            ray[:, :2] = xy
            ray[:, 2] = 1.0
            ray /= np.sqrt(np.einsum("ni,ni->n", ray, ray))[:, None]
            rays["r"] = (prob.centres_rf, np.einsum("nij,nj->ni", prob.R_rf_from_cf, ray))
        return rays["r"]

    def triangulation() -> tuple[Array, Array] | None:
        P, mi = prob.P_marks, prob.mi
        if prob.max_views_per_mark < 2:
            return None
        centres, d = get_rays()
        pts, ok = rays_intersection(centres, d, mi, P.shape[0], prob.mark_rows)
        n_ok = int(ok.sum())
        # Every mark triangulated: build_problem has already checked that they are not collinear.
        if n_ok < 3 or (n_ok < ok.size and collinearity(P[ok]) < COLLINEAR_RATIO):
            return None
        return align_points(P[ok], pts[ok])

    def dlt() -> tuple[Array, Array] | None:
        centres, d = get_rays()
        return generalized_dlt(centres, d, prob.pk.p_pf)

    def from_prior() -> tuple[Array, Array] | None:
        if prior is None:
            return None
        T = check_transform(prior, "initial_T_rf_from_pf")
        return T[:3, :3].copy(), T[:3, 3].copy()

    return [("triangulation", triangulation), ("generalized_dlt", dlt), ("prior", from_prior)]
