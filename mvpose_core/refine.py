"""The hot loop of pose estimation: packed observations, projection and Jacobian, LM solver.

Everything here works on a :class:`Packed` problem — one row per observation, every camera's
pose and intrinsics gathered per row — so one refinement iteration is a fixed, small number of
vectorised numpy calls whatever the number of cameras (no per-camera or per-point Python).

Parametrisation (used for the Jacobian and every covariance in mvpose_core): a pose
``T_rf_from_pf = (R, t)`` is perturbed on the right, in the part frame::

    T(δ) = T_rf_from_pf · Exp(δ),   δ = (ω [rad], v [mm]),   p_rf ≈ R (p + ω × p + v) + t

so ω is the rotation error about the part frame's axes and v the error of the part origin,
written in the part frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg.lapack import dposv

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Packed:
    """N observations with everything the residual needs, gathered per row."""

    R_cf_from_rf: Array  # [N, 3, 3]
    t_cf_from_rf: Array  # [N, 3]
    p_pf: Array  # [N, 3] mark centre in PF
    uv: Array  # [N, 2] observed distorted pixel
    weight: Array  # [N] 1 / σ (px⁻¹) of each observation
    f: Array  # [N, 2] fx, fy
    c: Array  # [N, 2] cx, cy
    k: Array  # [N, 8] k1 k2 p1 p2 k3 k4 k5 k6
    #: any of k4 k5 k6 non-zero (OpenCV's rational model); without them the denominator is 1
    rational: bool = True
    #: (K [3, 3], distortion) when every row has that one lens (the usual station): the
    #: projection and its derivative then come from one ``cv2.projectPoints`` call
    lens: tuple[Array, Array] | None = None
    #: d p / d δ = [−[p]× | I] per row ``[N, 3, 6]``, derived from ``p_pf``: the pose Jacobian
    #: is one product with it (the identity block copies d uv / d v exactly)
    dp_ddelta: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        p = self.p_pf
        m = np.zeros((p.shape[0], 3, 6))
        m[:, 0, 1], m[:, 0, 2] = p[:, 2], -p[:, 1]
        m[:, 1, 0], m[:, 1, 2] = -p[:, 2], p[:, 0]
        m[:, 2, 0], m[:, 2, 1] = p[:, 1], -p[:, 0]
        m[:, 0, 3] = m[:, 1, 4] = m[:, 2, 5] = 1.0
        object.__setattr__(self, "dp_ddelta", m)

    @property
    def n(self) -> int:
        return int(self.uv.shape[0])

    def with_measurements(self, uv: Array, weight: Array) -> Packed:
        """The same rows (cameras, marks) with other pixels and weights; nothing recomputed."""
        out = object.__new__(Packed)  # a shallow copy without copy.copy's generic machinery
        out.__dict__.update(self.__dict__, uv=uv, weight=weight)
        return out

    def with_poses(self, R_cf_from_rf: Array, t_cf_from_rf: Array) -> Packed:
        """The same rows (lenses, marks, pixels) seen from other camera poses."""
        out = object.__new__(Packed)
        out.__dict__.update(self.__dict__, R_cf_from_rf=R_cf_from_rf, t_cf_from_rf=t_cf_from_rf)
        return out

    def subset(self, rows: NDArray[np.intp] | NDArray[np.bool_]) -> Packed:
        return Packed(
            self.R_cf_from_rf[rows],
            self.t_cf_from_rf[rows],
            self.p_pf[rows],
            self.uv[rows],
            self.weight[rows],
            self.f[rows],
            self.c[rows],
            self.k[rows],
            self.rational,
            self.lens,
        )


def so3_exp(w: NDArray[np.floating[Any]]) -> Array:
    """Rotation matrix of a rotation vector (Rodrigues); scalar math, cheaper than scipy for one."""
    x, y, z = float(w[0]), float(w[1]), float(w[2])
    th2 = x * x + y * y + z * z
    if th2 < 1e-16:
        a, b = 1.0 - th2 / 6.0, 0.5 - th2 / 24.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    # I + a [w]× + b [w]×²
    return np.array(
        [
            [1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z],
            [a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z],
            [-a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y)],
        ]
    )


def project(pk: Packed, R: Array, t: Array) -> tuple[Array, Array]:
    """Predicted pixels ``[N, 2]`` and points in their camera frames ``[N, 3]``."""
    p_rf = pk.p_pf @ R.T + t
    p_cf = np.einsum("nij,nj->ni", pk.R_cf_from_rf, p_rf) + pk.t_cf_from_rf
    xy = p_cf[:, :2] / p_cf[:, 2:3]
    return _distort(pk, xy), p_cf


def _distort(pk: Packed, xy: Array) -> Array:
    k = pk.k
    x = xy[:, 0]
    y = xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k[:, 0] + r2 * (k[:, 1] + r2 * k[:, 4]))
    if pk.rational:
        radial = radial / (1.0 + r2 * (k[:, 5] + r2 * (k[:, 6] + r2 * k[:, 7])))
    p1 = k[:, 2]
    p2 = k[:, 3]
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1) * pk.f + pk.c


def residuals_and_jacobian(pk: Packed, R: Array, t: Array) -> tuple[Array, Array, Array]:
    """Residuals ``observed − predicted`` ``[N, 2]`` px, Jacobian ``[N, 2, 6]``, depths ``[N]``.

    The Jacobian is of the *predicted* pixels with respect to δ = (ω, v) (see the module
    docstring); the residual's Jacobian is its negative. Written for few numpy calls: this
    function is most of the solver's time.
    """
    A = pk.R_cf_from_rf @ R  # [N, 3, 3] R_cf_from_pf
    p_cf = (pk.R_cf_from_rf @ (pk.p_pf @ R.T + t)[:, :, None])[:, :, 0] + pk.t_cf_from_rf
    if pk.lens is not None:
        return _residuals_and_jacobian_cv(pk, A, p_cf)
    Z = p_cf[:, 2]
    iz = 1.0 / Z
    xy = p_cf[:, :2] * iz[:, None]
    x = xy[:, 0]
    y = xy[:, 1]
    k = pk.k
    xx = x * x
    yy = y * y
    xy2 = 2.0 * x * y
    r2 = xx + yy
    num = 1.0 + r2 * (k[:, 0] + r2 * (k[:, 1] + r2 * k[:, 4]))
    dnum = k[:, 0] + r2 * (2.0 * k[:, 1] + 3.0 * k[:, 4] * r2)
    if pk.rational:
        den = 1.0 + r2 * (k[:, 5] + r2 * (k[:, 6] + r2 * k[:, 7]))
        dden = k[:, 5] + r2 * (2.0 * k[:, 6] + 3.0 * k[:, 7] * r2)
        iden = 1.0 / den
        radial = num * iden
        drad2 = 2.0 * (dnum - radial * dden) * iden  # 2 · d radial / d r2
    else:
        radial = num
        drad2 = 2.0 * dnum
    p1 = k[:, 2]
    p2 = k[:, 3]
    pred = np.empty((pk.n, 2))
    pred[:, 0] = x * radial + p1 * xy2 + p2 * (r2 + 2.0 * xx)
    pred[:, 1] = y * radial + p1 * (r2 + 2.0 * yy) + p2 * xy2
    res = pk.uv - (pred * pk.f + pk.c)
    # D = d(xd, yd)/d(x, y); the off-diagonal terms are equal.
    off = 0.5 * xy2 * drad2 + 2.0 * (p1 * x + p2 * y)
    D = np.empty((pk.n, 2, 2))
    D[:, 0, 0] = radial + xx * drad2 + 2.0 * p1 * y + 6.0 * p2 * x
    D[:, 0, 1] = off
    D[:, 1, 0] = off
    D[:, 1, 1] = radial + yy * drad2 + 6.0 * p1 * y + 2.0 * p2 * x
    D *= (pk.f * iz[:, None])[:, :, None]
    # d(x, y)/d p_cf = [I2 | -xy] / Z, so d uv / d p_cf = [D | -D·xy]; times A: d uv / d v
    # ``[N, 2, 6]`` from B = d uv / d v ``[N, 2, 3]``: d p_cf / dω = −A [p]×.
    return res, (D @ (A[:, :2, :] - xy[:, :, None] * A[:, 2:3, :])) @ pk.dp_ddelta, Z


_NO_MOTION = np.zeros(3)


def _residuals_and_jacobian_cv(pk: Packed, A: Array, p_cf: Array) -> tuple[Array, Array, Array]:
    """:func:`residuals_and_jacobian` for rows sharing one lens, from points in their cameras.

    ``cv2.projectPoints`` with a zero pose projects the camera-frame points and returns, in
    columns 3–5 of its Jacobian, d uv / d t = d uv / d p_cf: one C call instead of the distortion
    model's thirty-odd numpy operations (same model, so the same values to rounding; tested).
    """
    assert pk.lens is not None
    K, dist = pk.lens
    uv, jac = cv2.projectPoints(p_cf, _NO_MOTION, _NO_MOTION, K, dist)
    res = pk.uv - uv.reshape(-1, 2)
    B = jac[:, 3:6].reshape(-1, 2, 3) @ A  # d uv / d v = d uv/d p_cf · A
    return res, B @ pk.dp_ddelta, p_cf[:, 2]  # d p_cf / dω = −A [p]×


@dataclass(frozen=True)
class LMResult:
    R: Array
    t: Array
    iterations: int
    initial_cost: float
    final_cost: float
    termination: str
    converged: bool
    residuals: Array  # [N, 2] observed − predicted at (R, t), px
    jacobian: Array  # [N, 2, 6] of the predicted pixels at (R, t), unweighted
    #: [N] depth of each mark in its camera (mm) at the last evaluated pose: (R, t) itself, or
    #: the iterate one converged step (< step_tol σ) before it
    depth: Array
    #: JᵀWJ (6x6) at ``jacobian`` with the observations' weights, the pose's information
    #: for the covariance; None for a robust loss (its H carries the IRLS weights)
    information: Array | None = None


def robust_weights(norm_px: Array, loss: str, huber_px: float) -> Array:
    """IRLS weight per observation from its residual length in px (Huber: 1 inside, h/s outside)."""
    if loss == "linear":
        return np.ones_like(norm_px)
    return np.minimum(1.0, huber_px / np.maximum(norm_px, 1e-300))


def robust_rho(norm_px: Array, loss: str, huber_px: float) -> Array:
    """ρ(s) per observation: s²/2, or Huber's h·s − h²/2 beyond h (s in px)."""
    if loss == "linear":
        return 0.5 * norm_px * norm_px
    return np.where(
        norm_px <= huber_px, 0.5 * norm_px * norm_px, huber_px * norm_px - 0.5 * huber_px**2
    )


def levenberg_marquardt(
    pk: Packed,
    R: Array,
    t: Array,
    *,
    loss: str = "linear",
    huber_px: float = 2.0,
    max_iterations: int = 50,
    step_tol: float = 1e-2,
    cost_tol: float = 1e-12,
) -> LMResult:
    """Minimise Σ w² ρ(‖observed − predicted‖) over the pose, starting at (R, t).

    Each iteration solves (H + λ·diag H) δ = g with H = JᵀJ, g = Jᵀr (whitened by the weights;
    IRLS weights for Huber). Step lengths are measured statistically, as √(δᵀHδ) in units of
    the estimate's own standard deviation. Converged ("step") when a proposed step is shorter
    than ``step_tol`` σ: it is then applied from the linear model (exact to O(step²), so the
    pose is still refined to ~step_tol² σ) and the residuals are moved to first order, without
    another evaluation; the Jacobian returned is the one at the previous iterate. Also converged
    when an accepted step lowers the cost by less than ``cost_tol`` relative ("cost"), or when
    no step lowers it at all ("no_decrease"). Otherwise "max_iterations".
    """
    w = pk.weight
    w2 = w * w
    robust = loss != "linear"
    # Equal weights (the usual case) factor out of H and g: skip the per-row products.
    w0 = float(w[0]) if not robust and bool((w == w[0]).all()) else None

    def evaluate(R_: Array, t_: Array) -> tuple[float, Array, Array, Array, Array, Array]:
        """Cost, H, g (whitened), residuals, Jacobian and depths at (R_, t_)."""
        res, J, Z = residuals_and_jacobian(pk, R_, t_)
        if w0 is not None:
            # [J | r] once: its Gram matrix holds H = JᵀJ, g = Jᵀr and rᵀr in one product.
            Jr = np.concatenate((J, res[:, :, None]), axis=2).reshape(-1, 7)
            M = Jr.T @ Jr
            return 0.5 * w0 * w0 * float(M[6, 6]), M[:6, :6], M[:6, 6], res, J, Z
        s = np.sqrt(np.einsum("ni,ni->n", res, res))
        cost = float(w2 @ robust_rho(s, loss, huber_px))
        # cost Σ w² ρ(|r|): its IRLS form weights each row by w·√(ψ(s)/s)
        iw = w * np.sqrt(robust_weights(s, loss, huber_px))
        Jw = (J * iw[:, None, None]).reshape(-1, 6)
        return cost, Jw.T @ Jw, Jw.T @ (res * iw[:, None]).reshape(-1), res, J, Z

    def cost_of(res: Array) -> float:
        if w0 is not None:
            return 0.5 * w0 * w0 * float(np.einsum("ni,ni->", res, res))
        s = np.sqrt(np.einsum("ni,ni->n", res, res))
        return float(w2 @ robust_rho(s, loss, huber_px))

    cost, H, g, res, J, Z = evaluate(R, t)
    initial = cost
    lam = 1e-6
    termination = "max_iterations"
    converged = False
    it = 0
    while it < max_iterations:
        it += 1
        # residual = observed − predicted and J is of predicted, so −∇cost = Jᵀr (= g).
        dH = H.flat[::7].copy()  # the diagonal
        accepted = False
        while lam < 1e10:
            A = H.copy()
            A.flat[::7] += lam * dH
            # LAPACK's Cholesky solve directly: np.linalg.solve's wrapper costs 3x the solve.
            _, delta, bad = dposv(A, g)
            if bad:  # not positive definite (a degenerate direction): damp more
                lam = max(lam * 10.0, 1e-9)
                continue
            # δᵀHδ is the step's squared length in units of the estimate's own σ (χ²).
            step2 = float(delta @ H @ delta)
            if step2 < step_tol * step_tol:
                # So small that the linear model is exact to O(step²): take it without paying
                # for an evaluation, and move the residuals to first order.
                t = t + R @ delta[3:]
                R = R @ so3_exp(delta[:3])
                res = res - J @ delta
                cost = cost_of(res)
                termination, converged = "step", True
                break
            R_new = R @ so3_exp(delta[:3])
            t_new = t + R @ delta[3:]
            new = evaluate(R_new, t_new)
            if new[0] <= cost:  # NaN compares False: rejected
                accepted = True
                break
            lam *= 10.0
        if converged:
            break
        if not accepted:
            termination, converged = "no_decrease", True
            break
        decrease = cost - new[0]
        R, t = R_new, t_new
        cost, H, g, res, J, Z = new
        lam = max(lam * 0.1, 1e-9)
        if decrease <= cost_tol * max(cost, 1e-300):
            termination, converged = "cost", True
            break
    # H is at ``J``'s pose (the step's linear move keeps it); with equal weights and no
    # robust loss it is the information JᵀWJ up to the factored-out w0².
    info = H * (w0 * w0) if w0 is not None else (H if not robust else None)
    return LMResult(R, t, it, initial, cost, termination, converged, res, J, Z, info)
