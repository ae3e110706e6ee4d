"""Joint reprojection refinement of hand-eye X, board pose Y, the rig and the intrinsics.

Every corner of every camera at every sample is predicted through the robot chain,
``uv = project_c(T_cfc_from_cf0 · inv(X) · M_i · Y · P)``, and the squared pixel error is
minimised over X, Y, each further camera's ``T_cfc_from_cf0`` and (optionally) each camera's
intrinsics. With intrinsics included, the robot poses pin down the focal length far better than
the board views alone, and the covariance of X accounts for the intrinsics' uncertainty.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.optimize import least_squares

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
class Refined:
    """Result of the joint reprojection refinement over a set of samples."""

    X: Array
    Y: Array
    cameras: dict[str, CameraModel]
    T_cfc_from_cf0: dict[str, Array]
    cov: Array  # parameters: X (rotation rad about X's target axes, translation mm), Y, ...
    sigma_px: float  # noise estimated from the residuals
    residuals: dict[str, Array]  # sample → ["N", 2] px over all cameras
    depth_mm: float  # mean distance camera–board


def _perturb(T0: Array, p: Array) -> Array:
    return make_transform(rotvec_to_matrix(p[:3]) @ T0[:3, :3], T0[:3, 3] + p[3:])


def _camera(c: CameraModel, p: Array) -> CameraModel:
    dist = tuple(float(a + b) for a, b in zip(c.dist, p[4:], strict=True))
    return CameraModel(c.fx + p[0], c.fy + p[1], c.cx + p[2], c.cy + p[3], c.width, c.height, dist)


def refine(
    problem: HandEyeProblem,
    X0: Array,
    Y0: Array,
    ids: Sequence[str] | None = None,
    intrinsics: bool = True,
) -> Refined:
    """Minimise the reprojection error over X, Y, the rig and (if ``intrinsics``) every camera's
    intrinsics, over the samples ``ids`` (default all)."""
    ids = sorted(problem.detections) if ids is None else list(ids)
    cams = list(problem.cameras)
    others = cams[1:]
    obs = [
        (sid, cid, problem.detections[sid][cid])
        for sid in ids
        for cid in cams
        if cid in problem.detections[sid]
    ]
    chains = {sid: problem.chain(sid) for sid in ids}
    pts = [d.object_points(problem.board) for _, _, d in obs]
    # All corners in one array, with the observation each belongs to, so one evaluation is a
    # few vectorised operations per camera instead of one small call per image.
    owner = np.concatenate([np.full(len(P), k) for k, P in enumerate(pts)])
    P_all = np.concatenate(pts)
    measured = np.concatenate([d.uv for _, _, d in obs])
    by_camera = {c: np.flatnonzero(np.array([obs[k][1] == c for k in owner])) for c in cams}
    sizes = [len(P) for P in pts]
    # Parameter layout: X, Y, one pose per further camera, then intrinsics per camera.
    rel_at = {c: 12 + 6 * k for k, c in enumerate(others)}
    n_pose = 12 + 6 * len(others)
    intr_at: dict[str, int] = {}
    n = n_pose
    if intrinsics:
        for c in cams:
            intr_at[c] = n
            n += 4 + len(problem.cameras[c].dist)
    scale = np.ones(n)
    for start in [0, 6, *rel_at.values()]:
        scale[start : start + 3] = 1e-3  # radians vs mm
    for c, start in intr_at.items():
        scale[start + 4 : start + 4 + len(problem.cameras[c].dist)] = 1e-3

    def unpack(p: Array) -> tuple[Array, Array, dict[str, Array], dict[str, CameraModel]]:
        rel = {cams[0]: problem.T_cfc_from_cf0[cams[0]]}
        rel.update(
            {c: _perturb(problem.T_cfc_from_cf0[c], p[rel_at[c] : rel_at[c] + 6]) for c in others}
        )
        models = {
            c: _camera(
                problem.cameras[c], p[intr_at[c] : intr_at[c] + 4 + len(problem.cameras[c].dist)]
            )
            if c in intr_at
            else problem.cameras[c]
            for c in cams
        }
        return _perturb(X0, p[:6]), _perturb(Y0, p[6:12]), rel, models

    def predict(p: Array) -> Array:
        X, Y, rel, models = unpack(p)
        iX = invert(X)
        T = np.array([compose(rel[cid], iX, chains[sid], Y) for sid, cid, _ in obs])[owner]
        p_cf = np.einsum("nij,nj->ni", T[:, :3, :3], P_all) + T[:, :3, 3]
        uv = np.empty_like(measured)
        for c, rows in by_camera.items():
            uv[rows] = models[c].project(p_cf[rows])
        return uv

    def fun(p: Array) -> Array:
        return (predict(p) - measured).ravel()

    sol = least_squares(fun, np.zeros(n), method="lm", x_scale=scale)
    X, Y, rel, models = unpack(sol.x)
    dof = max(sol.fun.size - n, 1)
    sigma2 = float(sol.fun @ sol.fun) / dof
    cov = sigma2 * np.linalg.pinv(sol.jac.T @ sol.jac)
    res: dict[str, list[Array]] = {}
    blocks = np.split(predict(sol.x) - measured, np.cumsum(sizes)[:-1])
    for r, (sid, _, _) in zip(blocks, obs, strict=True):
        res.setdefault(sid, []).append(r)
    depths = [compose(rel[cid], invert(X), chains[sid], Y)[2, 3] for sid, cid, _ in obs]
    return Refined(
        X=X,
        Y=Y,
        cameras=models,
        T_cfc_from_cf0=rel,
        cov=cov,
        sigma_px=float(np.sqrt(sigma2)),
        residuals={sid: np.concatenate(r) for sid, r in res.items()},
        depth_mm=float(np.mean(depths)),
    )


def sigma_of_x(cov: Array) -> tuple[float, float]:
    """1σ of X as (mm, deg): RSS of the translation and rotation standard deviations, which is
    the expected RMS of the translation and angle errors."""
    mm = float(np.sqrt(np.trace(cov[3:6, 3:6])))
    return mm, float(np.degrees(np.sqrt(np.trace(cov[:3, :3]))))
