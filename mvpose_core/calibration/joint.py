"""Hand-eye bundle adjustment: X, board pose Y, the rig, each flange pose as a measurement.

Every corner of every camera at every sample is predicted through the robot chain,
``uv = project_c(T_cfc_from_cf0 · inv(X) · M_i · Y · (s · P))``, where ``M_i`` comes from the
sample's flange pose ``A_i · Δ_i``: the recorded pose ``A_i`` times a correction ``Δ_i`` (rotation
vector ω about the flange axes, translation v in the flange frame). The corrections are parameters
with a prior: the robot's per-axis 1σ. The squared, weighted sum of pixel errors and of
corrections is minimised over X, Y, each further camera's ``T_cfc_from_cf0``, (optionally) the
board scale ``s`` and every ``Δ_i``. The intrinsics are held: a robot pose error must not be
absorbed by the camera model.

The weights (pixel σ, robot σ in mm and degrees) are estimated from the data by variance
components (Förstner): each group's weighted squared residuals over its redundancy. With weights
that fit the data the inverse normal matrix is the covariance of the estimate, robot pose errors
included.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import sparse

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, compose, invert, make_transform, rotvec_to_matrix

Mount = Literal["robot", "fixed"]


@dataclass(frozen=True)
class HandEyeProblem:
    """Everything the solvers need; every mapping is keyed by sample id, then camera id."""

    mount: Mount
    board: BoardSpec
    cameras: dict[str, CameraModel]  # first key is the reference camera CF0
    T_cfc_from_cf0: dict[str, Array]
    robot_poses: dict[str, Array]  # T_rf_from_gf per sample
    detections: dict[str, dict[str, Detection]]  # sample → camera → detection (found only)

    @property
    def reference(self) -> str:
        return next(iter(self.cameras))

    def chain(self, sid: str) -> Array:
        A = self.robot_poses[sid]
        return invert(A) if self.mount == "robot" else A


@dataclass(frozen=True)
class Weights:
    """1σ of one measurement in each group: a corner coordinate (px), a flange position axis
    (mm), a flange rotation axis (deg)."""

    px: float = 0.1
    robot_mm: float = 0.05
    robot_deg: float = 0.01


# Weights are never estimated below these: exact robot poses would otherwise drive the robot
# weight to infinity (and their effect on X is nil well before).
_FLOOR = Weights(px=1e-4, robot_mm=1e-4, robot_deg=1e-5)


@dataclass(frozen=True)
class Refined:
    """Result of the bundle adjustment over a set of samples."""

    X: Array
    Y: Array
    cameras: dict[str, CameraModel]
    T_cfc_from_cf0: dict[str, Array]
    cov: Array  # shared parameters: X (ω rad about X's target axes, v mm), Y, the rig, scale
    weights: Weights  # as used (estimated from the data when asked)
    redundancy: dict[str, float]  # per group: measurements minus their share of the parameters
    residuals: dict[str, Array]  # sample → ["N", 2] px over all cameras
    robot_corrections: dict[str, Array]  # sample → Δ_i as (ω deg xyz, v mm xyz)
    scale: float  # board scale factor (1.0 when not fitted)
    scale_sigma: float  # its 1σ (0.0 when not fitted)
    camera_sigma: dict[str, Array]  # 1σ of (fx, fy, cx, cy, distortion...) of refined cameras
    depth_mm: float  # mean distance camera–board
    x: Array  # every parameter at the solution (for warm starts)

    @property
    def sigma_px(self) -> float:
        return self.weights.px

    def robot_chi2(self) -> dict[str, float]:
        """Per sample: the squared flange-pose correction in units of the robot's 1σ."""
        w = self.weights
        return {
            sid: float(np.sum((c[:3] / w.robot_deg) ** 2) + np.sum((c[3:] / w.robot_mm) ** 2))
            for sid, c in self.robot_corrections.items()
        }


def _perturb(T0: Array, p: Array) -> Array:
    return make_transform(rotvec_to_matrix(p[:3]) @ T0[:3, :3], T0[:3, 3] + p[3:])


def _camera(c: CameraModel, p: Array) -> CameraModel:
    """``c`` with (fx, fy, cx, cy, distortion...) changed by the first values of ``p``."""
    k = len(c.dist)
    dist = tuple(float(a + b) for a, b in zip(c.dist, p[4 : 4 + k], strict=True))
    return CameraModel(c.fx + p[0], c.fy + p[1], c.cx + p[2], c.cy + p[3], c.width, c.height, dist)


def _rodrigues(w: Array) -> Array:
    """Rotation matrices ``["N", 3, 3]`` of rotation vectors ``["N", 3]`` (rad)."""
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-12
    k = w / np.where(small, 1.0, th)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K = K - np.transpose(K, (0, 2, 1))
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    R = np.eye(3) + s * K + (1.0 - c) * (K @ K)
    R[small] = np.eye(3) + _skew(w[small])
    return R


def _skew(w: Array) -> Array:
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    return K - np.transpose(K, (0, 2, 1))


def refine(
    problem: HandEyeProblem,
    X0: Array,
    Y0: Array,
    ids: Sequence[str] | None = None,
    weights: Weights = Weights(),
    estimate: bool = True,
    fit_scale: bool = False,
    start: Array | None = None,
    prior_dof: float = 20.0,
    intrinsics: bool = False,
) -> Refined:
    """Bundle adjustment over the samples ``ids`` (default all). With ``estimate`` the weights
    are re-estimated from the residuals until they agree with them (the given ``weights`` are
    the start); without, they are used as given. ``start`` is a parameter vector of an earlier
    solve of the same layout (a warm start). The robot's σ from the data is pooled with the
    given one, which counts as ``prior_dof`` degrees of freedom: a station rarely has the robot
    poses to estimate it alone (the images fix a flange position along the lens axis poorly)."""
    ids = sorted(problem.detections) if ids is None else list(ids)
    cams = list(problem.cameras)
    others = cams[1:]
    obs = [
        (sid, cid, problem.detections[sid][cid])
        for sid in ids
        for cid in cams
        if cid in problem.detections[sid]
    ]
    pts = [d.object_points(problem.board) for _, _, d in obs]
    sizes = [len(P) for P in pts]
    owner = np.concatenate([np.full(len(P), k) for k, P in enumerate(pts)])
    P_all = np.concatenate(pts)
    measured = np.concatenate([d.uv for _, _, d in obs])
    by_camera = {c: np.flatnonzero(np.array([obs[k][1] == c for k in owner])) for c in cams}
    sample_of_obs = np.array([ids.index(sid) for sid, _, _ in obs])
    # Parameter layout: X, Y, one pose per further camera, the scale, then Δ per sample.
    rel_at = {c: 12 + 6 * k for k, c in enumerate(others)}
    n_shared = 12 + 6 * len(others)
    intr_at: dict[str, int] = {}
    if intrinsics:
        for c in cams:
            intr_at[c] = n_shared
            n_shared += 4 + len(problem.cameras[c].dist)
    n_shared += 1 if fit_scale else 0
    scale_at = n_shared - 1 if fit_scale else -1
    pose_at = n_shared
    n = n_shared + 6 * len(ids)
    n_px = 2 * len(measured)
    m = n_px + 6 * len(ids)
    # The sample each residual row belongs to (for the grouped finite differences).
    row_sample = np.concatenate(
        [np.repeat(sample_of_obs[owner], 2), np.repeat(np.arange(len(ids)), 6)]
    )
    rot_rows = n_px + (6 * np.arange(len(ids))[:, None] + np.arange(3)).ravel()
    mm_rows = rot_rows + 3
    groups = {"px": np.arange(n_px), "robot_deg": rot_rows, "robot_mm": mm_rows}

    def unpack(p: Array) -> tuple[Array, Array, dict[str, Array], float]:
        rel = {cams[0]: problem.T_cfc_from_cf0[cams[0]]}
        rel.update(
            {c: _perturb(problem.T_cfc_from_cf0[c], p[rel_at[c] : rel_at[c] + 6]) for c in others}
        )
        s = 1.0 + (p[scale_at] if fit_scale else 0.0)
        return _perturb(X0, p[:6]), _perturb(Y0, p[6:12]), rel, s

    def models(p: Array) -> dict[str, CameraModel]:
        return {
            c: _camera(problem.cameras[c], p[intr_at[c] :]) if c in intr_at else problem.cameras[c]
            for c in cams
        }

    A_all = np.array([problem.robot_poses[sid] for sid in ids])
    cam_of_obs = [cid for _, cid, _ in obs]

    def chains(p: Array) -> Array:
        """``M_i`` of every sample from its corrected flange pose ``A_i · Δ_i``."""
        corr = p[pose_at:].reshape(-1, 6)
        D = np.zeros((len(ids), 4, 4))
        D[:, :3, :3] = _rodrigues(corr[:, :3])
        D[:, :3, 3] = corr[:, 3:]
        D[:, 3, 3] = 1.0
        A = A_all @ D
        if problem.mount == "fixed":
            return A
        Rt = np.transpose(A[:, :3, :3], (0, 2, 1))
        inv = np.zeros_like(A)
        inv[:, :3, :3] = Rt
        inv[:, :3, 3] = -np.einsum("nij,nj->ni", Rt, A[:, :3, 3])
        inv[:, 3, 3] = 1.0
        return inv

    def chain(sid: str, k: int, p: Array) -> Array:
        return chains(p)[k]

    def predict(p: Array) -> Array:
        X, Y, rel, s = unpack(p)
        iX = invert(X)
        M = chains(p)
        left = {c: rel[c] @ iX for c in cams}
        T = np.array([left[c] for c in cam_of_obs]) @ M[sample_of_obs] @ Y
        R, t = T[owner, :3, :3], T[owner, :3, 3]
        p_cf = np.einsum("nij,nj->ni", R, s * P_all) + t
        uv = np.empty_like(measured)
        cam_models = models(p)
        for c, rows in by_camera.items():
            uv[rows] = cam_models[c].project(p_cf[rows])
        return uv

    def residuals(p: Array, w: Weights) -> Array:
        corr = p[pose_at:].reshape(-1, 6)
        prior = np.concatenate([corr[:, :3] / np.radians(w.robot_deg), corr[:, 3:] / w.robot_mm], 1)
        return np.concatenate([((predict(p) - measured) / w.px).ravel(), prior.ravel()])

    max_iterations = 30
    steps = np.full(n, 1e-4)  # mm
    for at in [0, 6, *rel_at.values()]:
        steps[at : at + 3] = 1e-7  # rad
    steps[pose_at:].reshape(-1, 6)[:, :3] = 1e-7
    for c, at in intr_at.items():
        steps[at : at + 4] = 1e-4  # px
        steps[at + 4 : at + 4 + len(problem.cameras[c].dist)] = 1e-8
    if fit_scale:
        steps[scale_at] = 1e-8

    pose_rows = np.arange(m)
    pose_cols_base = pose_at + 6 * row_sample

    def jacobian(p: Array, w: Weights, f0: Array) -> sparse.csr_matrix:
        # Forward differences; a sample's Δ touches only its own rows, so each component of
        # every sample's Δ is differenced at once (6 evaluations instead of 6·N). Sparse, so the
        # products below stay small and single-threaded.
        shared = np.empty((m, n_shared))
        for j in range(n_shared):
            e = np.zeros(n)
            e[j] = steps[j]
            shared[:, j] = (residuals(p + e, w) - f0) / steps[j]
        vals, cols = [], []
        for k in range(6):
            e = np.zeros(n)
            e[pose_at + k :: 6] = steps[pose_at + k]
            vals.append((residuals(p + e, w) - f0) / steps[pose_at + k])
            cols.append(pose_cols_base + k)
        J_shared = sparse.csr_matrix(shared)
        J_pose = sparse.csr_matrix(
            (np.concatenate(vals), (np.tile(pose_rows, 6), np.concatenate(cols))), shape=(m, n)
        )
        return sparse.hstack([J_shared, J_pose[:, n_shared:]], format="csr")

    def gauss_newton(x: Array, w: Weights) -> tuple[Array, Array, sparse.csr_matrix]:
        """Levenberg–Marquardt on the normal equations (a few hundred parameters at most)."""
        f = residuals(x, w)
        cost = float(f @ f)
        lam = 1e-4
        J = jacobian(x, w, f)
        for _ in range(max_iterations):
            N, g = (J.T @ J).toarray(), J.T @ f
            d = np.diag(N).copy()
            while True:
                dx = -_solve(N + lam * np.diag(d), g, n_shared)
                f_new = residuals(x + dx, w)
                c_new = float(f_new @ f_new)
                if c_new <= cost or lam > 1e6:
                    break
                lam *= 10.0
            if c_new > cost:
                break  # no step lowers the cost: at the minimum within rounding
            x, f, done = x + dx, f_new, cost - c_new <= 1e-9 * cost + 1e-12
            cost, lam = c_new, max(lam / 10.0, 1e-9)
            J = jacobian(x, w, f)
            if done:
                break
        return x, f, J

    w = weights
    x = np.zeros(n) if start is None else np.array(start, dtype=float)
    red: dict[str, float] = {}
    for _ in range(max_iterations if estimate else 1):
        x, v, J = gauss_newton(x, w)
        N_inv = _inverse((J.T @ J).toarray(), n_shared)
        factors: dict[str, float] = {}
        for g, rows in groups.items():
            Jg = J[rows]
            # Redundancy of the group: its measurements minus their share of the parameters.
            red[g] = float(len(rows) - np.sum(N_inv * (Jg.T @ Jg).toarray()))
            factors[g] = float(np.sqrt(v[rows] @ v[rows] / red[g])) if red[g] > 3 else 1.0
        if not estimate:
            break
        new = _blend(w, weights, factors, red, prior_dof)
        keys = ("px", "robot_mm", "robot_deg")
        done = all(abs(getattr(new, k) / getattr(w, k) - 1.0) < 0.01 for k in keys)
        w = new
        if done:
            break
    X, Y, rel, s = unpack(x)
    res: dict[str, list[Array]] = {}
    blocks = np.split(predict(x) - measured, np.cumsum(sizes)[:-1])
    for r, (sid, _, _) in zip(blocks, obs, strict=True):
        res.setdefault(sid, []).append(r)
    corr = x[pose_at:].reshape(-1, 6)
    depths = [
        compose(rel[cid], invert(X), chain(sid, k, x), Y)[2, 3]
        for (sid, cid, _), k in zip(obs, sample_of_obs, strict=True)
    ]
    return Refined(
        X=X,
        Y=Y,
        cameras=models(x),
        T_cfc_from_cf0=rel,
        cov=N_inv[:n_shared, :n_shared],
        weights=w,
        redundancy=red,
        residuals={sid: np.concatenate(r) for sid, r in res.items()},
        robot_corrections={
            sid: np.r_[np.degrees(corr[k, :3]), corr[k, 3:]] for k, sid in enumerate(ids)
        },
        scale=s,
        scale_sigma=float(np.sqrt(N_inv[scale_at, scale_at])) if fit_scale else 0.0,
        camera_sigma={
            c: np.sqrt(np.diag(N_inv)[at : at + 4 + len(problem.cameras[c].dist)])
            for c, at in intr_at.items()
        },
        depth_mm=float(np.mean(depths)),
        x=x,
    )


def _blend(
    w: Weights, stated: Weights, factors: dict[str, float], red: dict[str, float], dof: float
) -> Weights:
    """Next weights: the pixel σ from the residuals, the robot's pooled with the stated σ."""
    out = {}
    for k in ("px", "robot_mm", "robot_deg"):
        s2 = (getattr(w, k) * factors[k]) ** 2  # the group's variance as the data tell it
        if k != "px":
            s2 = (dof * getattr(stated, k) ** 2 + red[k] * s2) / (dof + red[k])
        out[k] = max(float(np.sqrt(s2)), getattr(_FLOOR, k))
    return Weights(**out)


def _blocks(N: Array, s: int) -> tuple[Array, Array, Array]:
    """The normal matrix's shared block ``A``, its coupling ``B`` ``["s", "K", 6]`` and the
    inverses of the per-sample 6×6 blocks (they couple with nothing but the shared ones)."""
    K = (N.shape[0] - s) // 6
    idx = s + 6 * np.arange(K)[:, None] + np.arange(6)
    D = N[idx[:, :, None], idx[:, None, :]]
    return N[:s, :s], N[:s, s:].reshape(s, K, 6), np.asarray(np.linalg.inv(D), dtype=float)


# The normal equations are solved by the Schur complement on the shared parameters: small
# batched inverses and einsum, so no multithreaded BLAS call spins on a busy machine.


def _solve(N: Array, g: Array, s: int) -> Array:
    A, B, Di = _blocks(N, s)
    gp = g[s:].reshape(-1, 6)
    BDi = np.einsum("skj,kji->ski", B, Di)
    S = A - np.einsum("ski,tki->st", BDi, B)
    xs = np.linalg.inv(S) @ (g[:s] - np.einsum("ski,ki->s", BDi, gp))
    xp = np.einsum("kij,kj->ki", Di, gp - np.einsum("ski,s->ki", B, xs))
    return np.concatenate([xs, xp.ravel()])


def _inverse(N: Array, s: int) -> Array:
    A, B, Di = _blocks(N, s)
    K = Di.shape[0]
    BDi = np.einsum("skj,kji->ski", B, Di)
    Si = np.linalg.inv(A - np.einsum("ski,tki->st", BDi, B))
    top = -np.einsum("st,tki->ski", Si, BDi).reshape(s, 6 * K)
    lower = np.einsum("ski,st,tlj->kilj", BDi, Si, BDi).reshape(6 * K, 6 * K)
    idx = 6 * np.arange(K)[:, None] + np.arange(6)
    lower[idx[:, :, None], idx[:, None, :]] += Di
    return np.block([[Si, top], [top.T, lower]])


def without_scale(r: Refined) -> Array:
    """``r.x`` with the scale parameter taken out (a warm start for a solve at scale 1)."""
    n_shared = r.cov.shape[0]
    return np.delete(r.x, n_shared - 1)


def sigma_of_x(cov: Array) -> tuple[float, float]:
    """1σ of X as (mm, deg): RSS of the translation and rotation standard deviations, which is
    the expected RMS of the translation and angle errors."""
    mm = float(np.sqrt(np.trace(cov[3:6, 3:6])))
    return mm, float(np.degrees(np.sqrt(np.trace(cov[:3, :3]))))
