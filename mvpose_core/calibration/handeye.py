"""Hand-eye calibration: the paper's eq. 10, AX = XB cross-checked, joint refinement, covariance.

Three ways in: the paper's board-in-robot-frame method (eq. 10), OpenCV's five AX = XB solvers
checked against each other, and a final bundle adjustment over all samples that takes each
flange pose as a measurement with the robot's σ (:mod:`mvpose_core.calibration.joint`).

One problem shape covers both mounts. With ``M_i`` the robot chain of sample ``i``:

    robot-mounted camera:  T_cf_from_bf = inv(X) · M_i · Y,  X = T_gf_from_cf, Y = T_rf_from_bf,
                           M_i = T_gf_from_rf = inv(T_rf_from_gf)
    fixed camera, board on the flange:
                           T_cf_from_bf = inv(X) · M_i · Y,  X = T_rf_from_cf, Y = T_gf_from_bf,
                           M_i = T_rf_from_gf

X is the pose of the reference camera CF0; other cameras of a rig follow through their fixed
``T_cfc_from_cf0`` (from stereo calibration) and add their observations to the refinement.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.intrinsics import board_pose, require_samples, split_detections
from mvpose_core.calibration.joint import (
    HandEyeProblem,
    Mount,
    Refined,
    Weights,
    refine,
    sigma_of_x,
    without_scale,
)
from mvpose_core.calibration.outliers import find_outliers, find_pose_outliers
from mvpose_core.calibration.robotposes import check_motion, match_ids
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import (
    Array,
    apply,
    compose,
    invert,
    make_transform,
    transform_error,
)

METHODS: dict[str, int] = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "andreff": cv2.CALIB_HAND_EYE_ANDREFF,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}


@dataclass(frozen=True)
class HandEyeOptions:
    """Limits of the hand-eye solve; the defaults suit industrial robots and 0.05–0.5 px images."""

    min_samples: int = 5
    max_translation_mm: float = 3000.0  # a camera farther than this from the flange is implausible
    max_fixed_distance_mm: float = 20000.0  # same for a fixed camera and the robot base
    # The robot's stated accuracy per pose and axis (datasheet or station file), the prior of
    # each flange pose; the data refine it (pooled with robot_prior_dof degrees of freedom).
    robot_sigma_mm: float = 0.05
    robot_sigma_deg: float = 0.01
    robot_prior_dof: float = 20.0
    # Refine the intrinsics with the hand-eye (the images hold their information, the robot
    # poses are weighted as the measurements they are); off to hold them (e.g. from --base).
    refine_intrinsics: bool = True
    # Closed forms further than this and more than 3σ from the final are flagged.
    agree_mm: float = 2.0
    agree_deg: float = 0.2
    # Above these after the adjustment the poses do not fit the images: robot pose errors give
    # a few px at most, inverted poses or a wrong convention tens of px or mm.
    max_rms_px: float = 10.0
    max_robot_mm: float = 2.0  # estimated robot scatter per axis
    max_robot_deg: float = 0.2
    # A board whose scale (fitted against the robot's motion) is off by more than 3σ and more
    # than this fraction is refused: the square size is not the printed one.
    max_scale_error: float = 5e-4
    min_excess_px: float = 0.1  # a sample's RMS must exceed the median by this to be an outlier


@dataclass(frozen=True)
class MethodCheck:
    """One solver's answer and how it compares with the refined result."""

    T: Array | None
    status: str  # "ok", "NaN", "implausible: ...", "disagrees: ..."
    deg: float = float("nan")
    mm: float = float("nan")


@dataclass(frozen=True)
class HandEyeResult:
    """Hand-eye transform X, board pose Y, their uncertainty and every cross-check."""

    mount: Mount
    reference: str
    X: Array  # T_gf_from_cf0 (robot) or T_rf_from_cf0 (fixed)
    Y: Array  # T_rf_from_bf (robot) or T_gf_from_bf (fixed)
    sigma_mm: float  # 1σ of X's translation (RSS over axes), from the weighted covariance
    sigma_deg: float  # 1σ of X's rotation angle
    depth_mm: float
    methods: dict[str, MethodCheck]
    per_sample_rms_px: dict[str, float]
    residuals: dict[str, Array]
    cov: Array
    cameras: dict[str, CameraModel]  # intrinsics as written (refined or held)
    T_cfc_from_cf0: dict[str, Array]  # rig after the adjustment
    weights: Weights  # σ of a pixel and of the robot per axis, as estimated from the data
    stated: Weights  # the robot σ given as the prior
    scale: float  # board scale fitted against the robot motion (before it is held at 1)
    scale_sigma: float
    robot_corrections: dict[str, Array]  # sample → flange correction (ω deg xyz, v mm xyz)
    intrinsics_refined: bool
    camera_sigma: dict[str, Array]  # 1σ of (fx, fy, cx, cy, distortion...) when refined
    rejected: dict[str, str] = field(default_factory=dict)
    left_out: dict[str, str] = field(default_factory=dict)  # outlier samples: id → why
    warnings: list[str] = field(default_factory=list)

    @property
    def sigma_px(self) -> float:
        return self.weights.px

    @property
    def rms_px(self) -> float:
        r = np.concatenate(list(self.residuals.values()))
        return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


# --------------------------------------------------------------------------- closed forms


def board_pose_from_points(
    board: BoardSpec, corner_ids: Sequence[int], p_rf: Array
) -> tuple[Array, float]:
    """``T_rf_from_bf`` from board corners measured in RF (e.g. touched with a pointer tool),
    and the RMS fit residual in mm."""
    p_rf = np.asarray(p_rf, dtype=float).reshape(-1, 3)
    ids = np.asarray(corner_ids, dtype=int)
    if ids.shape[0] != p_rf.shape[0] or ids.shape[0] < 3:
        raise CalibrationError(
            f"board pose from points: need >= 3 corners with one RF point each, got "
            f"{ids.shape[0]} ids and {p_rf.shape[0]} points"
        )
    p_bf = board.object_points[ids]
    if np.linalg.matrix_rank(p_bf - p_bf.mean(0), tol=1e-6) < 2:
        raise CalibrationError(f"board pose from points: corners {ids.tolist()} are collinear")
    cb, cr = p_bf.mean(0), p_rf.mean(0)
    rot, _ = Rotation.align_vectors(p_rf - cr, p_bf - cb)
    T = make_transform(rot.as_matrix(), cr - rot.apply(cb))
    rms = float(np.sqrt(np.mean(np.sum((apply(T, p_bf) - p_rf) ** 2, axis=1))))
    return T, rms


def mean_transform(Ts: Sequence[Array]) -> Array:
    """Chordal mean rotation and mean translation."""
    R = Rotation.from_matrix(np.array([T[:3, :3] for T in Ts])).mean().as_matrix()
    return make_transform(R, np.mean([T[:3, 3] for T in Ts], axis=0))


def handeye_board_in_robot(
    robot_poses: Mapping[str, Array], T_cf_from_bf: Mapping[str, Array], T_rf_from_bf: Array
) -> tuple[Array, dict[str, Array]]:
    """The paper's eq. 10 per sample and their mean:
    ``T_gf_from_cf = inv(T_rf_from_gf) · T_rf_from_bf · inv(T_cf_from_bf)``."""
    per = {
        sid: compose(invert(robot_poses[sid]), T_rf_from_bf, invert(T_cf_from_bf[sid]))
        for sid in sorted(T_cf_from_bf)
    }
    return mean_transform(list(per.values())), per


def solve_axxb(chains: Sequence[Array], T_cf_from_bf: Sequence[Array], method: str) -> Array | None:
    """X from one OpenCV hand-eye solver (None if it produced NaN)."""
    inv_chain = [invert(M) for M in chains]
    R, t = cv2.calibrateHandEye(
        [T[:3, :3] for T in inv_chain],
        [T[:3, 3] for T in inv_chain],
        [T[:3, :3] for T in T_cf_from_bf],
        [T[:3, 3] for T in T_cf_from_bf],
        method=METHODS[method],
    )
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None
    # Some solvers return a slightly non-orthogonal matrix; project to the nearest rotation.
    # On inconsistent poses some return a reflection or a null matrix: no answer, not a crash.
    if not np.linalg.det(R) > 0.5:
        return None
    return make_transform(Rotation.from_matrix(R).as_matrix(), t.reshape(3))


# --------------------------------------------------------------------------- driver


def screen(
    candidates: Mapping[str, Array | None], mount: Mount, options: HandEyeOptions
) -> tuple[dict[str, MethodCheck], dict[str, Array]]:
    """Mark NaN and implausible solver answers; return the checks and the plausible answers."""
    checks: dict[str, MethodCheck] = {}
    plausible: dict[str, Array] = {}
    robot = mount == "robot"
    limit = options.max_translation_mm if robot else options.max_fixed_distance_mm
    for name, X in candidates.items():
        if X is None:
            checks[name] = MethodCheck(None, "NaN")
        elif np.linalg.norm(X[:3, 3]) > limit:
            checks[name] = MethodCheck(
                X,
                f"implausible: camera {np.linalg.norm(X[:3, 3]):.0f} mm from the "
                f"{'flange' if mount == 'robot' else 'robot base'}",
            )
        else:
            plausible[name] = X
    return checks, plausible


def calibrate_handeye(
    problem: HandEyeProblem,
    options: HandEyeOptions = HandEyeOptions(),
    T_rf_from_bf: Array | None = None,
    rejected: Mapping[str, str] | None = None,
) -> HandEyeResult:
    """Solve X and Y: closed forms (all five AX = XB solvers, plus the paper's eq. 10 when the
    board pose in RF is known) as the start, then the bundle adjustment that takes every flange
    pose as a measurement with the robot's σ. Outlier samples are left out (and named); a board
    scale the robot motion contradicts, or robot poses that do not fit the images, are refused."""
    what = f"hand-eye ({problem.mount} camera {problem.reference!r})"
    ref = problem.reference
    ids = sorted(sid for sid, dets in problem.detections.items() if ref in dets)
    require_samples(len(ids), options.min_samples, what, ids)
    cam = problem.cameras[ref]
    B = {sid: board_pose(cam, problem.detections[sid][ref], problem.board) for sid in ids}
    check_motion({sid: problem.robot_poses[sid] for sid in ids}, B, what)
    chains = [problem.chain(sid) for sid in ids]
    candidates: dict[str, Array | None] = {
        name: solve_axxb(chains, [B[s] for s in ids], name) for name in METHODS
    }
    if T_rf_from_bf is not None:
        if problem.mount != "robot":
            raise CalibrationError(
                f"{what}: the board-in-robot-frame method is for robot-mounted cameras"
            )
        candidates["paper_eq10"], _ = handeye_board_in_robot(problem.robot_poses, B, T_rf_from_bf)
    checks, plausible = screen(candidates, problem.mount, options)
    if not plausible:
        raise CalibrationError(
            f"{what}: no solver gave a plausible answer: "
            + "; ".join(f"{k}: {v.status}" for k, v in checks.items())
            + "; robot poses in the wrong convention or exported inverted (T_gf_from_rf)?"
        )

    # Start from the medoid: the answer closest to all others, robust to one bad solver.
    def spread(n: str) -> float:
        return sum(sum(transform_error(plausible[n], plausible[o])[1:]) for o in plausible)

    X0 = plausible[min(plausible, key=spread)]
    if T_rf_from_bf is not None and problem.mount == "robot":
        Y0 = T_rf_from_bf
    else:
        Y0 = mean_transform([compose(invert(problem.chain(s)), X0, B[s]) for s in ids])
    stated = Weights(0.1, options.robot_sigma_mm, options.robot_sigma_deg)
    used = [s for s in sorted(problem.detections)]
    left_out: dict[str, str] = {}
    warnings: list[str] = []
    # Outliers and the board scale are judged with the scale free; the result holds it at 1.
    while True:
        scaled = refine(
            problem, X0, Y0, used, stated, fit_scale=True,
            intrinsics=options.refine_intrinsics, prior_dof=options.robot_prior_dof,
        )  # fmt: skip
        _check_fit(scaled, options, what)
        rms = {
            sid: float(np.sqrt(np.mean(np.sum(v * v, axis=1))))
            for sid, v in scaled.residuals.items()
        }
        med = float(np.median(list(rms.values())))
        why: dict[str, list[str]] = {}
        for sid in find_outliers(rms, min_excess_px=options.min_excess_px):
            why.setdefault(sid, []).append(f"reprojection RMS {rms[sid]:.2f} px (median {med:.2f})")
        for sid in find_pose_outliers(scaled.robot_chi2()):
            c = scaled.robot_corrections[sid]
            why.setdefault(sid, []).append(
                f"robot pose off the fit by {np.linalg.norm(c[3:]):.2f} mm / "
                f"{np.linalg.norm(c[:3]):.3f}° (the others: robot σ "
                f"{scaled.weights.robot_mm:.3f} mm / {scaled.weights.robot_deg:.4f}° per axis)"
            )
        bad = {sid: ", ".join(reasons) for sid, reasons in why.items()}
        if not bad:
            break
        left_out.update(bad)
        used = [s for s in used if s not in bad]
        if len(used) < options.min_samples:
            raise CalibrationError(
                f"{what}: too few samples left after leaving out the outliers "
                + "; ".join(f"{k}: {v}" for k, v in sorted(left_out.items()))
                + f": {len(used)} remain, need at least {options.min_samples}"
            )
        warnings.append(
            "left out outlier samples " + "; ".join(f"{k} ({v})" for k, v in sorted(bad.items()))
        )
    scale_error = scaled.scale - 1.0
    if abs(scale_error) > 3.0 * scaled.scale_sigma:
        msg = (
            f"the robot motion says the board is {scaled.scale:.5f} ± {scaled.scale_sigma:.5f} "
            f"(1σ) times its declared size ({problem.board}): measure the printed board and "
            "give its measured square size"
        )
        if abs(scale_error) > options.max_scale_error:
            raise CalibrationError(f"{what}: {msg}")
        warnings.append(msg)
    r = refine(
        problem, X0, Y0, used, scaled.weights, intrinsics=options.refine_intrinsics,
        start=without_scale(scaled), prior_dof=options.robot_prior_dof,
    )  # fmt: skip
    _check_fit(r, options, what)
    s_mm, s_deg = sigma_of_x(r.cov)
    for name, X in plausible.items():
        deg, mm = transform_error(X, r.X)
        lim_deg, lim_mm = max(options.agree_deg, 3 * s_deg), max(options.agree_mm, 3 * s_mm)
        ok = deg <= lim_deg and mm <= lim_mm
        checks[name] = MethodCheck(
            X,
            "ok" if ok else (
                f"disagrees: {deg:.3f}° {mm:.2f} mm (more than {lim_deg:.3f}° / {lim_mm:.2f} mm); "
                "the closed forms weigh every robot pose alike: look for single robot poses "
                "far off the fit (largest flange corrections in the report)"
            ),
            deg,
            mm,
        )  # fmt: skip
    if r.weights.robot_mm > 2 * stated.robot_mm or r.weights.robot_deg > 2 * stated.robot_deg:
        warnings.append(
            f"the robot poses scatter {r.weights.robot_mm:.3f} mm / {r.weights.robot_deg:.4f}° "
            f"per axis, more than the stated {stated.robot_mm:g} mm / {stated.robot_deg:g}°; "
            "the 1σ counts it (pooled with the stated σ)"
        )
    return HandEyeResult(
        mount=problem.mount,
        reference=ref,
        X=r.X,
        Y=r.Y,
        sigma_mm=s_mm,
        sigma_deg=s_deg,
        depth_mm=r.depth_mm,
        methods={k: checks[k] for k in candidates},
        per_sample_rms_px={
            sid: float(np.sqrt(np.mean(np.sum(v * v, axis=1)))) for sid, v in r.residuals.items()
        },
        residuals=r.residuals,
        cov=r.cov,
        cameras=r.cameras,
        T_cfc_from_cf0=r.T_cfc_from_cf0,
        weights=r.weights,
        stated=stated,
        scale=scaled.scale,
        scale_sigma=scaled.scale_sigma,
        robot_corrections=r.robot_corrections,
        intrinsics_refined=options.refine_intrinsics,
        camera_sigma=r.camera_sigma,
        rejected=dict(rejected or {}),
        left_out=left_out,
        warnings=warnings,
    )


def _check_fit(r: Refined, options: HandEyeOptions, what: str) -> None:
    """Refuse robot poses that do not fit the images (the flange corrections or the pixels)."""
    res = np.concatenate(list(r.residuals.values()))
    rms = float(np.sqrt(np.mean(np.sum(res * res, axis=1))))
    w = r.weights
    if (
        rms > options.max_rms_px
        or w.robot_mm > options.max_robot_mm
        or (w.robot_deg > options.max_robot_deg)
    ):
        raise CalibrationError(
            f"{what}: the robot poses do not fit the images: they scatter {w.robot_mm:.2f} mm / "
            f"{w.robot_deg:.3f}° per axis around the fit (limit {options.max_robot_mm:g} mm / "
            f"{options.max_robot_deg:g}°), reprojection RMS {rms:.1f} px (limit "
            f"{options.max_rms_px:g} px); wrong robot convention, poses exported inverted "
            "(T_gf_from_rf), or poses and images paired wrongly?"
        )


def build_problem(
    mount: Mount,
    board: BoardSpec,
    cameras: Mapping[str, CameraModel],
    robot_poses: Mapping[str, Array],
    detections: Mapping[str, Mapping[str, Detection | None]],
    T_cfc_from_cf0: Mapping[str, Array] | None = None,
    min_corners: int = 6,
) -> tuple[HandEyeProblem, dict[str, str]]:
    """Pair images with robot poses by sample id; samples without a usable board are left out and
    reported (id → reason), never shifted onto a neighbour. ``detections`` is camera → sample."""
    if list(cameras) != list(detections):
        raise CalibrationError(
            f"hand-eye: cameras {list(cameras)} but detections for {list(detections)}"
        )
    ref = next(iter(cameras))
    rel = dict(T_cfc_from_cf0 or {})
    rel.setdefault(ref, np.eye(4))
    missing = [c for c in cameras if c not in rel]
    if missing:
        raise CalibrationError(f"hand-eye: no T_cfc_from_cf0 (stereo result) for cameras {missing}")
    per_sample: dict[str, dict[str, Detection]] = {sid: {} for sid in robot_poses}
    rejected: dict[str, str] = {}
    for cid, dets in detections.items():
        match_ids(robot_poses, dets, f"hand-eye camera {cid!r}")
        used, rej = split_detections(dets, min_corners, f"hand-eye camera {cid!r}")
        for sid, d in used.items():
            per_sample[sid][cid] = d
        for sid, why in rej.items():
            rejected[sid] = (rejected[sid] + "; " if sid in rejected else "") + f"{cid}: {why}"
    # A sample counts if any camera saw the board; the others' misses are still reported.
    rejected = {
        sid: why if not per_sample[sid] else f"{why} (other cameras used)"
        for sid, why in rejected.items()
    }
    problem = HandEyeProblem(
        mount=mount,
        board=board,
        cameras=dict(cameras),
        T_cfc_from_cf0={c: rel[c] for c in cameras},
        robot_poses={sid: robot_poses[sid] for sid in per_sample if per_sample[sid]},
        detections={sid: d for sid, d in per_sample.items() if d},
    )
    return problem, rejected
