"""Initial pose: 3D alignment to triangulated marks, or a linear generalised-camera DLT on rays.

Two starts, chosen by what the layout offers (see :func:`mvpose_core.estimate.estimate_pose`):

* **alignment** — three or more non-collinear marks triangulated: the rotation and translation
  that best map the CAD positions onto the triangulated points (Kabsch/Umeyama without scale,
  SVD with the determinant fixed to +1).
* **generalised DLT** — marks seen by one camera only (fixed stations without overlap): each
  ray (centre c, direction d in RF) of a mark at p in PF gives ``d × (R p + t − c) = 0``, linear in
  the 12 entries of (R, t). With six or more rays in general position the 3N×12 system has a
  unique least-squares solution (not homogeneous, because the rays do not share one centre);
  R is then projected onto SO(3) and t re-solved with R fixed. It needs cameras with distinct
  centres and marks not all in one plane through a degenerate configuration; callers check the
  result's reprojection error.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dgesdd, dposv

from mvpose_core.refine import Array

#: second singular value / first of centred positions below this counts as collinear
COLLINEAR_RATIO = 1e-3


def collinearity(points: Array) -> float:
    """Ratio of the second to the first singular value of centred points (0 = on one line)."""
    c = points - points.mean(axis=0)
    ev = np.linalg.eigvalsh(c.T @ c)  # squared singular values, ascending
    return float(np.sqrt(max(ev[1], 0.0) / ev[2])) if ev[2] > 0 else 0.0


def _nearest_rotation(M: Array) -> Array:
    U, _, Vt, code = dgesdd(M)  # LAPACK directly: numpy's wrapper doubles a 3x3 SVD's cost
    if code != 0:
        raise np.linalg.LinAlgError(f"SVD did not converge (LAPACK info {code})")
    R = U @ Vt
    # det(R) is ±1: the sign of the triple product of its rows (scalar arithmetic, 3x3).
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0.0:
        R = (U * np.array([1.0, 1.0, -1.0])) @ Vt  # flip the least significant axis
    return R


def align_points(p_pf: Array, p_rf: Array) -> tuple[Array, Array]:
    """(R, t) minimising Σ‖R p_pf + t − p_rf‖² for ``[K, 3]`` pairs, K ≥ 3 non-collinear."""
    if p_pf.shape[0] < 3:
        raise ValueError(f"3D alignment needs at least 3 points, got {p_pf.shape[0]}")
    # np.add.reduce / n is what ndarray.mean computes, without its ~5 µs of dispatch per call
    n = p_pf.shape[0]
    mu_pf = np.add.reduce(p_pf, axis=0) / n
    mu_rf = np.add.reduce(p_rf, axis=0) / n
    H = (p_pf - mu_pf).T @ (p_rf - mu_rf)
    R = _nearest_rotation(H.T)
    return R, mu_rf - R @ mu_pf


#: ``d @ _SKEW`` reshaped to [N, 3, 3] is [d]× of each row d: ([d]×)_ij = −ε_ijk d_k
_SKEW = -np.array(
    [[[0, 0, 0], [0, 0, 1], [0, -1, 0]], [[0, 0, -1], [0, 0, 0], [1, 0, 0]],
     [[0, 1, 0], [-1, 0, 0], [0, 0, 0]]], dtype=float,
).transpose(2, 0, 1).reshape(3, 9)


def generalized_dlt(centres: Array, directions: Array, p_pf: Array) -> tuple[Array, Array] | None:
    """Linear pose from N ≥ 6 rays (RF) of marks at ``p_pf``; None when the system is degenerate."""
    n = p_pf.shape[0]
    if n < 6:
        return None
    # Normalise for conditioning: marks about their centroid and size, rays about their centre.
    mu_p = np.add.reduce(p_pf, axis=0) / p_pf.shape[0]
    q = p_pf - mu_p
    scale = float(np.sqrt(np.einsum("ni,ni->", q, q) / n)) or 1.0
    q /= scale
    mu_c = np.add.reduce(centres, axis=0) / centres.shape[0]
    c = centres - mu_c
    d = directions
    Dx = (d @ _SKEW).reshape(n, 3, 3)  # [d]× per ray
    # unknowns: M = scale·R (row-major, 9) and s = R mu_p + t − mu_c (3): [d]× (M q + s) = [d]× c;
    # (M q)_i = Σ_j M_ij q_j, so column 3 i + j of a ray's 3 rows is column i of [d]× times q_j.
    A = np.concatenate([(Dx[:, :, :, None] * q[:, None, None, :]).reshape(n, 3, 9), Dx], axis=2)
    b = (Dx @ c[:, :, None]).reshape(-1)
    U, S, Vt, code = dgesdd(A.reshape(3 * n, 12), full_matrices=0)  # LAPACK directly (see above)
    if code != 0 or S[-1] < 1e-9 * S[0]:
        return None
    x = Vt.T @ ((U.T @ b) / S)
    M = x[:9].reshape(3, 3)
    if not np.all(np.isfinite(M)) or np.linalg.norm(M) < 1e-12:
        return None
    R = _nearest_rotation(M)
    # Re-solve the translation with the rotation fixed: Σ [d]×ᵀ[d]× s = Σ [d]×ᵀ[d]× w with
    # w = c − scale·R q, and [d]×ᵀ[d]× = |d|² I − d dᵀ (3 × 3 normal equations).
    w = c - scale * q @ R.T
    dd = np.einsum("ni,ni->n", d, d)
    lhs = dd.sum() * np.eye(3) - d.T @ d
    rhs = dd @ w - d.T @ np.einsum("ni,ni->n", d, w)
    _, s, bad = dposv(lhs, rhs)
    if bad:  # every ray parallel: the translation along them is free
        return None
    return R, s + mu_c - R @ mu_p
