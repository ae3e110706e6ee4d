"""Images-only bundle adjustment of cameras that see common board placements: each camera's pose
relative to a reference camera, every placement, optionally the intrinsics, and the covariance
that gives each relation its 1σ.

Used by the stereo step (two cameras on one rig) and the fixed-station step (a group of cameras
linked through shared placements). No robot pose enters: the relations come from pixels alone.
Parameters: per camera other than the reference a rotation vector (left-multiplied, in the
reference frame) and a translation (added) of ``T_ref_from_cf``; per camera, with intrinsics,
changes of (fx, fy, cx, cy, distortion...); per placement the same six of ``T_ref_from_bf``.
The covariance is σ²(JᵀJ)⁻¹ at the solution with σ² from the residuals (m − n degrees of
freedom), so with intrinsics adjusted it includes their uncertainty.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import sparse
from scipy.linalg import cho_factor, cho_solve

from mvpose_core.calibration.boards import BoardSpec, Detection
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.handeye import mean_transform
from mvpose_core.calibration.intrinsics import board_pose
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import Array, compose, invert, make_transform, rotvec_to_matrix

_MAX_ITERATIONS = 100


@dataclass(frozen=True)
class CameraGroup:
    """Cameras related to each other through shared board placements."""

    reference: str
    T_ref_from_cf: dict[str, Array]
    T_ref_from_bf: dict[str, Array]  # every placement seen by the group
    residuals: dict[str, Array]  # sample → ["N", 2] px over the group's cameras
    cameras: dict[str, CameraModel] = field(default_factory=dict)  # after the adjustment
    #: 6×6 covariance of each camera's (rotation vector rad, translation mm) in ``T_ref_from_cf``
    #: (zeros for the reference camera)
    cov: dict[str, Array] = field(default_factory=dict)
    #: per camera 1σ of (fx, fy, cx, cy, distortion...) when the intrinsics were adjusted
    intrinsics_sd: dict[str, Array] = field(default_factory=dict)
    sigma_px: float = float("nan")  # pixel σ estimated from the residuals
    intrinsics_adjusted: bool = False

    def sigma(self, camera: str) -> tuple[float, float]:
        """1σ of ``T_ref_from_cf`` as (mm, deg): RSS over the axes, i.e. the expected RMS of the
        camera's position error and rotation angle relative to the reference camera."""
        c = self.cov[camera]
        return float(np.sqrt(np.trace(c[3:, 3:]))), float(np.degrees(np.sqrt(np.trace(c[:3, :3]))))

    def sigma_distance(self, camera: str) -> float:
        """1σ (mm) of the distance between ``camera`` and the reference (a stereo baseline)."""
        t = self.T_ref_from_cf[camera][:3, 3]
        n = float(np.linalg.norm(t))
        if n == 0.0:
            return 0.0
        u = t / n
        return float(np.sqrt(u @ self.cov[camera][3:, 3:] @ u))


def _skew(a: Array) -> Array:
    """Cross-product matrices ``["N", 3, 3]`` of vectors ``["N", 3]``."""
    K = np.zeros((len(a), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -a[:, 2], a[:, 1], -a[:, 0]
    return K - np.transpose(K, (0, 2, 1))


def _observe(
    cam: CameraModel, T_ref_from_cf: Array, T_ref_from_bf: Array, P: Array
) -> tuple[Array, Array, Array, Array]:
    """Projections ``["N", 2]`` of board points ``P`` and their Jacobians (rows u0 v0 u1 …) with
    respect to the camera's six pose parameters, the placement's six and the intrinsics.

    The pose parameters are a rotation vector applied on the left and an added translation, at
    zero: ``p_cf = Rcᵀ(q − tc)`` with ``q = Rb·P + tb``, so ∂p/∂ω_c = Rcᵀ[q − tc]×,
    ∂p/∂t_c = −Rcᵀ, ∂p/∂ω_b = −Rcᵀ[Rb·P]×, ∂p/∂t_b = Rcᵀ. OpenCV's projection Jacobian with
    respect to the translation at zero pose is ∂uv/∂p, and it gives the intrinsics' columns
    (fx, fy, cx, cy, distortion…) directly."""
    Rc, tc = T_ref_from_cf[:3, :3], T_ref_from_cf[:3, 3]
    Rb, tb = T_ref_from_bf[:3, :3], T_ref_from_bf[:3, 3]
    a = P @ Rb.T
    x = a + tb - tc
    p = x @ Rc
    zero = np.zeros(3)
    uv, jac = cv2.projectPoints(p, zero, zero, cam.K, cam.dist_array)
    n = len(P)
    Jp = jac[:, 3:6].reshape(n, 2, 3)
    JpR = Jp @ Rc.T  # ∂uv/∂(a point in the reference frame)
    J_cam = np.concatenate([JpR @ _skew(x), -JpR], axis=2).reshape(2 * n, 6)
    J_bf = np.concatenate([-(JpR @ _skew(a)), JpR], axis=2).reshape(2 * n, 6)
    return uv.reshape(n, 2).astype(float), J_cam, J_bf, np.asarray(jac[:, 6:], dtype=float)


def _normal(J: sparse.csr_matrix, r: Array) -> tuple[Array, Array, Array]:
    """Normal equations of the column-scaled Jacobian: ``N``, the gradient and the scales.

    Built from the sparse Jacobian: a dense product would run multi-threaded BLAS, which on a
    busy machine spins far longer than the product takes."""
    scale = 1.0 / np.maximum(np.sqrt(np.asarray(J.multiply(J).sum(axis=0)).ravel()), 1e-300)
    Js = J @ sparse.diags(scale)
    return (Js.T @ Js).toarray(), Js.T @ r, scale


def _update(T: Array, p: Array) -> Array:
    return make_transform(rotvec_to_matrix(p[:3]) @ T[:3, :3], T[:3, 3] + p[3:])


def _camera(c: CameraModel, p: Array) -> CameraModel:
    dist = tuple(float(a + b) for a, b in zip(c.dist, p[4:], strict=True))
    return CameraModel(c.fx + p[0], c.fy + p[1], c.cx + p[2], c.cy + p[3], c.width, c.height, dist)


def _chain(
    detections: Mapping[str, Mapping[str, Detection]],
    B: Mapping[tuple[str, str], Array],
    reference: str,
) -> dict[str, Array]:
    """``T_ref_from_cf`` of every camera reachable from the reference through shared samples
    (breadth first; each link the mean over the shared samples' PnP poses)."""
    T_ref_from_cf = {reference: np.eye(4)}
    frontier = [reference]
    while frontier:
        known = frontier.pop(0)
        for cid in detections:
            if cid in T_ref_from_cf:
                continue
            shared = sorted(set(detections[known]) & set(detections[cid]))
            if shared:
                links = [
                    compose(T_ref_from_cf[known], B[(known, s)], invert(B[(cid, s)]))
                    for s in shared
                ]
                T_ref_from_cf[cid] = mean_transform(links)
                frontier.append(cid)
    return T_ref_from_cf


def adjust_group(
    board: BoardSpec,
    cameras: Mapping[str, CameraModel],
    detections: Mapping[str, Mapping[str, Detection]],
    reference: str,
    refine_intrinsics: bool = True,
) -> CameraGroup:
    """Bundle adjustment of the cameras reachable from ``reference`` through shared placements;
    ``detections`` is camera → sample → found board. Cameras not reachable are left out of the
    group (the caller forms another group of them)."""
    B = {
        (cid, sid): board_pose(cameras[cid], d, board)
        for cid, per in detections.items()
        for sid, d in per.items()
    }
    T_ref_from_cf = _chain(detections, B, reference)
    cams = [c for c in detections if c in T_ref_from_cf]
    samples = sorted({s for c in cams for s in detections[c]})
    T_ref_from_bf = {
        s: mean_transform(
            [compose(T_ref_from_cf[c], B[(c, s)]) for c in cams if s in detections[c]]
        )
        for s in samples
    }
    movable = [c for c in cams if c != reference]
    obs = [(c, sid, detections[c][sid]) for c in cams for sid in samples if sid in detections[c]]
    pts = [d.object_points(board) for _, _, d in obs]
    col: dict[tuple[str, str], int] = {}
    n_par = 0
    for c in movable:
        col[("cam", c)] = n_par
        n_par += 6
    n_intr = {c: 4 + len(cameras[c].dist) for c in cams}
    if refine_intrinsics:
        for c in cams:
            col[("intr", c)] = n_par
            n_par += n_intr[c]
    for sid in samples:
        col[("bf", sid)] = n_par
        n_par += 6
    n_res = sum(2 * len(d) for _, _, d in obs)
    if n_res <= n_par:
        raise CalibrationError(
            f"cameras {cams}: {n_res} corner coordinates cannot fix {n_par} parameters; "
            "take more board placements"
        )
    tc = dict(T_ref_from_cf)
    tb = dict(T_ref_from_bf)
    models = {c: cameras[c] for c in cams}

    def evaluate(with_jacobian: bool) -> tuple[Array, sparse.csr_matrix]:
        r = np.empty(n_res)
        rows: list[np.ndarray] = []
        cols: list[np.ndarray] = []
        vals: list[Array] = []
        row = 0
        for (c, sid, d), P in zip(obs, pts, strict=True):
            uv, J_cam, J_bf, J_in = _observe(models[c], tc[c], tb[sid], P)
            n = 2 * len(d)
            r[row : row + n] = (uv - d.uv).ravel()
            if with_jacobian:
                blocks = [(col[("bf", sid)], J_bf)]
                if c != reference:
                    blocks.append((col[("cam", c)], J_cam))
                if refine_intrinsics:
                    blocks.append((col[("intr", c)], J_in))
                for k, B in blocks:
                    rr, cc = np.meshgrid(np.arange(row, row + n), np.arange(k, k + B.shape[1]))
                    rows.append(rr.T.ravel())
                    cols.append(cc.T.ravel())
                    vals.append(B.ravel())
            row += n
        if not with_jacobian:
            return r, sparse.csr_matrix((n_res, n_par))
        J = sparse.csr_matrix(
            (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
            shape=(n_res, n_par),
        )
        return r, J

    def step(dx: Array) -> None:
        for c in movable:
            k = col[("cam", c)]
            tc[c] = _update(tc[c], dx[k : k + 6])
        if refine_intrinsics:
            for c in cams:
                k = col[("intr", c)]
                models[c] = _camera(models[c], dx[k : k + n_intr[c]])
        for sid in samples:
            k = col[("bf", sid)]
            tb[sid] = _update(tb[sid], dx[k : k + 6])

    # Levenberg–Marquardt with the normal equations, relinearised at every accepted step (the
    # Jacobian above holds at zero perturbation); the columns are scaled, since focal lengths
    # (px) and rotations (rad) differ by six orders of magnitude.
    r, J = evaluate(True)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(_MAX_ITERATIONS):
        N, g, scale = _normal(J, r)
        saved = (dict(tc), dict(tb), dict(models))
        try:
            dx = -scale * cho_solve(cho_factor(N + lam * np.diag(np.diag(N))), g)
        except np.linalg.LinAlgError:
            lam *= 10.0
            if lam > 1e8:
                break
            continue
        step(dx)
        r_new, _ = evaluate(False)
        new = float(r_new @ r_new)
        if new < cost:
            done = cost - new < 1e-12 * cost
            r, cost, lam = r_new, new, max(lam / 10.0, 1e-12)
            _, J = evaluate(True)
            if done:
                break
        else:
            tc, tb, models = saved
            lam *= 10.0
            if lam > 1e8:
                break
    s2 = cost / (n_res - n_par)
    N, _, scale = _normal(J, r)
    try:
        inv = cho_solve(cho_factor(N), np.eye(n_par))
    except np.linalg.LinAlgError:
        raise CalibrationError(
            f"cameras {cams}: the board placements do not fix every camera's pose and "
            "intrinsics (tilt the board more, reach the image corners)"
        ) from None
    cov_all = s2 * (scale[:, None] * inv * scale[None, :])
    cov = {reference: np.zeros((6, 6))}
    for c in movable:
        k = col[("cam", c)]
        cov[c] = cov_all[k : k + 6, k : k + 6]
    sd = np.sqrt(np.diag(cov_all))
    intr_sd = {
        c: sd[col[("intr", c)] : col[("intr", c)] + n_intr[c]] for c in cams if refine_intrinsics
    }
    res: dict[str, list[Array]] = {}
    row = 0
    for _, sid, d in obs:
        n = 2 * len(d)
        res.setdefault(sid, []).append(r[row : row + n].reshape(-1, 2))
        row += n
    return CameraGroup(
        reference=reference,
        T_ref_from_cf={c: tc[c] for c in cams},
        T_ref_from_bf=tb,
        residuals={sid: np.concatenate(v) for sid, v in res.items()},
        cameras=models,
        cov=cov,
        intrinsics_sd=intr_sd,
        sigma_px=float(np.sqrt(s2)),
        intrinsics_adjusted=refine_intrinsics,
    )
