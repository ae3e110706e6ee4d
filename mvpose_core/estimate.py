"""Multi-view 6-DoF pose of a part from mark observations in every camera of every view.

``estimate_pose`` works in the robot base frame RF (every camera posed in RF by
:mod:`mvpose_core.scene`) and returns ``T_rf_from_pf``. Steps:

1. validate the input at this edge (shapes, NaN, unknown cameras/marks, duplicates, too few or
   collinear marks) — :class:`PoseInputError` names the problem;
2. start: 3D alignment to marks triangulated from two or more rays, else a generalised-camera
   DLT on single rays, else the caller's prior (``initial_T_rf_from_pf``) — see
   :mod:`mvpose_core.initial`;
3. refine: Levenberg–Marquardt on the reprojection error of every observation in every camera
   (the paper's eq. 15 over both cameras of each rig), or the paper's left-camera-only objective;
   optional Huber loss and outlier rejection (rule in :class:`EstimateOptions`);
4. covariance from the final Jacobian (parametrisation in :mod:`mvpose_core.uncertainty`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from mvpose_core.gate import ReasonCode
from mvpose_core.initial import COLLINEAR_RATIO, align_points, collinearity, generalized_dlt
from mvpose_core.refine import Array, LMResult, Packed, levenberg_marquardt, residuals_and_jacobian
from mvpose_core.scene import ViewCamera
from mvpose_core.transforms import check_transform, make_transform
from mvpose_core.triangulate import rays_intersection
from mvpose_core.uncertainty import information_from_jacobian, invert_information


class PoseInputError(ValueError):
    """The estimator refuses its input; ``reason`` is the gate code the server reports."""

    def __init__(self, message: str, reason: ReasonCode = ReasonCode.BAD_INPUT) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class Observation:
    """One detected mark centre in one image: distorted pixel ``uv`` ``[2]``."""

    view: int
    camera_id: str
    mark_id: str
    uv: np.ndarray
    sigma_px: float | None = None  # per-observation σ; None = the call's sigma_px

    @property
    def key(self) -> tuple[int, str, str]:
        return (self.view, self.camera_id, self.mark_id)


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
    #: converged when a step is below this many σ of the estimate (see refine.levenberg_marquardt)
    step_tol: float = 1e-4
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
    initial_cost: float  # ½ Σ ρ(|r|/σ)² at the start
    final_cost: float
    rms_px: float  # √(mean |r|²) over the observations used, px (OpenCV's RMS)
    termination: str  # "gradient" | "step" | "cost" | "no_decrease" | "max_iterations"
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


# ----------------------------------------------------------------------------- packing


def _camera_arrays(cameras: Sequence[ViewCamera]) -> tuple[dict[tuple[int, str], int], tuple]:
    index: dict[tuple[int, str], int] = {}
    for i, c in enumerate(cameras):
        if (c.view, c.camera_id) in index:
            raise PoseInputError(f"camera v{c.view}/{c.camera_id} is listed twice")
        index[(c.view, c.camera_id)] = i
    T = np.asarray([c.T_rf_from_cf for c in cameras], dtype=float)
    if T.shape != (len(cameras), 4, 4) or not np.all(np.isfinite(T)):
        raise PoseInputError("every camera needs a finite 4x4 T_rf_from_cf")
    R_cf_from_rf = np.transpose(T[:, :3, :3], (0, 2, 1))
    t_cf_from_rf = -np.einsum("cij,cj->ci", R_cf_from_rf, T[:, :3, 3])
    f = np.array([(c.model.fx, c.model.fy) for c in cameras])
    cc = np.array([(c.model.cx, c.model.cy) for c in cameras])
    k = np.array([tuple(c.model.dist) + (0.0,) * (8 - len(c.model.dist)) for c in cameras])
    left = np.array([c.rig_position == 0 for c in cameras])
    return index, (R_cf_from_rf, t_cf_from_rf, f, cc, k, left, T)


def _mark_array(marks_pf: Mapping[str, np.ndarray], ids: Sequence[str]) -> Array:
    out = np.empty((len(ids), 3))
    for i, m in enumerate(ids):
        if m not in marks_pf:
            raise PoseInputError(f"observation names unknown mark {m!r}")
        p = np.asarray(marks_pf[m], dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise PoseInputError(
                f"mark {m!r}: position must be 3 finite values (mm), got {p.tolist()}"
            )
        out[i] = p
    return out


def pack_layout(
    cameras: Sequence[ViewCamera],
    marks_pf: Mapping[str, np.ndarray],
    layout: Sequence[tuple[int, str, str]],
    objective: str = "all",
) -> tuple[Packed, np.ndarray]:
    """Pack a layout of (view, camera_id, mark_id) with zero pixels; rows kept by ``objective``."""
    index, (Rc, tc, f, cc, k, left, _) = _camera_arrays(cameras)
    ci = np.empty(len(layout), dtype=np.intp)
    for n, (v, cid, _m) in enumerate(layout):
        if (v, cid) not in index:
            raise PoseInputError(f"layout names unknown camera v{v}/{cid}")
        ci[n] = index[(v, cid)]
    p = _mark_array(marks_pf, [m for _, _, m in layout])
    rows = np.arange(len(layout)) if objective == "all" else np.flatnonzero(left[ci])
    ci = ci[rows]
    pk = Packed(
        Rc[ci],
        tc[ci],
        p[rows],
        np.zeros((rows.size, 2)),
        np.ones(rows.size),
        f[ci],
        cc[ci],
        k[ci],
        bool(np.any(k[:, 5:])),
    )
    return pk, rows


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
    if not (np.isfinite(sigma_px) and sigma_px > 0):
        raise PoseInputError(f"sigma_px must be a positive number of pixels, got {sigma_px}")
    n = len(observations)
    index, (Rc, tc, f, cc, k, left, T_rf_from_cf) = _camera_arrays(cameras)
    ci = np.empty(n, dtype=np.intp)
    weight = np.full(n, 1.0 / sigma_px)
    seen: set[tuple[int, str, str]] = set()
    try:
        uv = np.array([o.uv for o in observations], dtype=float).reshape(n, 2)
        fast = bool(np.all(np.isfinite(uv)))
    except (ValueError, TypeError):
        fast = False
    for i, o in enumerate(observations):
        key = (o.view, o.camera_id)
        j = index.get(key)
        if j is None:
            raise PoseInputError(
                f"observation v{o.view}/{o.camera_id}/{o.mark_id}: no camera v{o.view}/"
                f"{o.camera_id} in this station"
            )
        ci[i] = j
        okey = (o.view, o.camera_id, o.mark_id)
        if okey in seen:
            raise PoseInputError(
                f"observation v{o.view}/{o.camera_id}/{o.mark_id}: the same mark is observed "
                "twice in one image"
            )
        seen.add(okey)
        if o.sigma_px is not None:
            if not (np.isfinite(o.sigma_px) and o.sigma_px > 0):
                raise PoseInputError(
                    f"observation v{o.view}/{o.camera_id}/{o.mark_id}: sigma_px must be > 0, "
                    f"got {o.sigma_px}"
                )
            weight[i] = 1.0 / o.sigma_px
    if not fast:
        # Slow path only to name the culprit.
        for o in observations:
            name = f"observation v{o.view}/{o.camera_id}/{o.mark_id}"
            u = np.asarray(o.uv, dtype=float)
            if u.shape != (2,):
                raise PoseInputError(f"{name}: uv must have shape (2,), got {u.shape}")
            if not np.all(np.isfinite(u)):
                raise PoseInputError(f"{name}: uv contains NaN or infinite values {u.tolist()}")
    mark_ids = sorted({o.mark_id for o in observations})
    if len(mark_ids) < 3:
        raise PoseInputError(
            f"too few marks: a pose needs at least 3 distinct marks, "
            f"got {len(mark_ids)} {mark_ids}",
            ReasonCode.TOO_FEW_MARKS,
        )
    P_marks = _mark_array(marks_pf, mark_ids)
    ratio = collinearity(P_marks)
    if ratio < COLLINEAR_RATIO:
        raise PoseInputError(
            f"marks {mark_ids} are collinear (spread ratio {ratio:.1e}): rotation about their "
            "line is undetermined",
            ReasonCode.POSE_NOT_DETERMINED,
        )
    mi = np.array([mark_ids.index(o.mark_id) for o in observations], dtype=np.intp)
    pk_all = Packed(
        Rc[ci], tc[ci], P_marks[mi], uv, weight, f[ci], cc[ci], k[ci], bool(np.any(k[:, 5:]))
    )
    objective = np.ones(n, dtype=bool) if options.objective == "all" else left[ci]
    if len(set(mi[objective].tolist())) < 3:
        raise PoseInputError(
            f"too few marks for the {options.objective} objective: "
            f"{sorted({mark_ids[j] for j in mi[objective]})}",
            ReasonCode.TOO_FEW_MARKS,
        )

    starts = _starts(observations, cameras, ci, mi, P_marks, T_rf_from_cf, initial_T_rf_from_pf)
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
        pk = pk_all.subset(active)
        lm = _refine(pk, start, options)
        iterations += lm.iterations
        # A mirrored minimum with marks behind the cameras can fit well: rank it last.
        in_front = bool(np.all(_depths(pk, lm) > 0))
        if best is None or (in_front, -lm.final_cost) > (best_in_front, -best[0].final_cost):
            best, best_in_front = (lm, name), in_front
        if in_front and _rms(lm) <= options.restart_rms_px:
            break
    if best is None:
        raise PoseInputError(
            "no start for the pose: need 3 non-collinear marks each seen by two cameras, or 6 "
            "single observations in general position, or a prior pose",
            ReasonCode.POSE_NOT_DETERMINED,
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
            rejected.append(observations[worst].key)
            lm = _refine(pk_all.subset(active), (lm.R, lm.t), options)
            iterations += lm.iterations

    if active.all():
        res, J = lm.residuals, lm.jacobian
        depth = _depths(pk_all, lm)
    else:
        res, J, depth = residuals_and_jacobian(pk_all, lm.R, lm.t)
    behind = np.flatnonzero(~(depth > 0))
    if behind.size:
        o = observations[int(behind[0])]
        raise PoseInputError(
            f"mark {o.mark_id!r} would be behind camera v{o.view}/{o.camera_id} "
            f"(depth {depth[behind[0]]:.1f} mm): wrong camera, mark or camera pose",
            ReasonCode.MARK_BEHIND_CAMERA,
        )
    Jw = J[active] * pk_all.weight[active][:, None, None]
    try:
        cov = invert_information(information_from_jacobian(Jw))
    except ValueError as err:
        raise PoseInputError(str(err), ReasonCode.POSE_NOT_DETERMINED) from None
    r_act = res[active]
    info = SolveInfo(
        iterations=iterations,
        initial_cost=initial_cost,
        final_cost=lm.final_cost,
        rms_px=float(np.sqrt(np.mean(np.sum(r_act * r_act, axis=1)))),
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


def _depths(pk: Packed, lm: LMResult) -> Array:
    return (
        np.einsum("nj,nj->n", pk.R_cf_from_rf[:, 2, :], pk.p_pf @ lm.R.T + lm.t)
        + pk.t_cf_from_rf[:, 2]
    )


def _rms(lm: LMResult) -> float:
    return float(np.sqrt(np.mean(np.sum(lm.residuals * lm.residuals, axis=1))))


Start = Callable[[], "tuple[Array, Array] | None"]


def _starts(
    observations: Sequence[Observation],
    cameras: Sequence[ViewCamera],
    ci: NDArray[np.intp],
    mi: NDArray[np.intp],
    P_marks: Array,
    T_rf_from_cf: Array,
    prior: np.ndarray | None,
) -> list[tuple[str, Start]]:
    """Candidate starts in order of preference, each computed only when asked for."""
    rays: dict[str, tuple[Array, Array]] = {}

    def get_rays() -> tuple[Array, Array]:
        if not rays:
            uv = np.array([o.uv for o in observations], dtype=float)
            # One undistortion call per distinct lens model (usually one for the whole station).
            xy = np.empty_like(uv)
            groups: dict[tuple[float, ...], list[int]] = {}
            for c in np.unique(ci).tolist():
                m = cameras[c].model
                groups.setdefault((m.fx, m.fy, m.cx, m.cy, *m.dist), []).append(c)
            for members in groups.values():
                rows = np.isin(ci, members)
                xy[rows] = cameras[members[0]].model.undistort_normalized(uv[rows])
            ray = np.concatenate([xy, np.ones((len(ci), 1))], axis=1)
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            d = np.einsum("nij,nj->ni", T_rf_from_cf[ci, :3, :3], ray)
            rays["r"] = (T_rf_from_cf[ci, :3, 3], d)
        return rays["r"]

    def triangulation() -> tuple[Array, Array] | None:
        if np.bincount(mi).max() < 2:
            return None
        centres, d = get_rays()
        pts, ok = rays_intersection(centres, d, mi, P_marks.shape[0])
        if ok.sum() < 3 or collinearity(P_marks[ok]) < COLLINEAR_RATIO:
            return None
        return align_points(P_marks[ok], pts[ok])

    def dlt() -> tuple[Array, Array] | None:
        centres, d = get_rays()
        return generalized_dlt(centres, d, P_marks[mi])

    def from_prior() -> tuple[Array, Array] | None:
        if prior is None:
            return None
        T = check_transform(prior, "initial_T_rf_from_pf")
        return T[:3, :3].copy(), T[:3, 3].copy()

    return [("triangulation", triangulation), ("generalized_dlt", dlt), ("prior", from_prior)]
