"""What the recipe predicts for each mark in an image: its ellipse, window and centre correction.

The image of a circle is (up to lens distortion) an ellipse whose centre is not the image of the
circle's centre. Both the expected ellipse and the correction come from the same computation: the
circle's rim is sampled in 3D at the given pose, projected through the lens, and an ellipse is
fitted to it exactly as the detector fits one to edge points (:func:`fit_ellipses`). The
correction alone, at the estimated pose, is :mod:`mvpose_core.detect.correction`'s.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.scene import ProjectedMark, ViewCamera, sighted_marks
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, compose, invert

_RIM_SAMPLES = 72


@lru_cache(maxsize=8)
def _cos_sin(n: int) -> Array:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    cs = np.stack([np.cos(t), np.sin(t)], axis=1)
    cs.flags.writeable = False
    return cs


@dataclass(frozen=True)
class Ellipse:
    """Centre (px), semi-axes (px, a ≥ b) and the angle of the major axis (rad, from +u)."""

    centre: Array
    a: float
    b: float
    angle: float

    @property
    def radius(self) -> float:
        return float(np.sqrt(self.a * self.b))

    @property
    def axis_ratio(self) -> float:
        return self.b / self.a

    def radius_towards(self, phi: Array) -> Array:
        """Distance from the centre to the ellipse along directions ``phi`` (rad)."""
        d = phi - self.angle
        return self.a * self.b / np.hypot(self.b * np.cos(d), self.a * np.sin(d))

    def distances(self, pts: Array) -> Array:
        """Approximate signed distances (px, + outside) of points ``["N", 2]`` to the ellipse."""
        c, s = np.cos(self.angle), np.sin(self.angle)
        dx, dy = pts[:, 0] - self.centre[0], pts[:, 1] - self.centre[1]
        x, y = c * dx + s * dy, -s * dx + c * dy
        q = np.sqrt((x / self.a) ** 2 + (y / self.b) ** 2) + 1e-12
        grad = np.sqrt((x / self.a**2) ** 2 + (y / self.b**2) ** 2) / q + 1e-12
        return (q - 1.0) / grad


@dataclass(frozen=True)
class Ellipses:
    """A batch of ellipses as arrays: centres ``["C", 2]``, semi-axes and angles ``["C"]``."""

    centre: Array
    a: Array
    b: Array
    angle: Array
    valid: Array | None = None  # which fits succeeded (None: all)

    @classmethod
    def of(cls, items: list[Ellipse]) -> Ellipses:
        return cls(
            np.array([e.centre for e in items], dtype=float),
            np.array([e.a for e in items], dtype=float),
            np.array([e.b for e in items], dtype=float),
            np.array([e.angle for e in items], dtype=float),
        )

    def __getitem__(self, k: int) -> Ellipse:
        return Ellipse(
            self.centre[k].copy(), float(self.a[k]), float(self.b[k]), float(self.angle[k])
        )

    @property
    def radius(self) -> Array:
        return np.sqrt(self.a * self.b)

    @property
    def ok(self) -> np.ndarray:
        """``["C"]`` bool: which fits succeeded."""
        return np.ones(len(self.a), dtype=bool) if self.valid is None else self.valid

    def radius_towards(self, phi: Array) -> Array:
        """``["C", "R"]`` distances from each centre to its ellipse along directions ``phi``
        (``["R"]`` for all, or ``["C", "R"]``)."""
        d = (phi if phi.ndim == 2 else phi[None, :]) - self.angle[:, None]
        a, b = self.a[:, None], self.b[:, None]
        return a * b / np.hypot(b * np.cos(d), a * np.sin(d))

    def distances(self, pts: Array) -> Array:
        """Approximate signed distances ``["C", "N"]`` of points ``["C", "N", 2]`` (+ outside)."""
        c, s = np.cos(self.angle)[:, None], np.sin(self.angle)[:, None]
        dx, dy = pts[..., 0] - self.centre[:, 0, None], pts[..., 1] - self.centre[:, 1, None]
        x, y = c * dx + s * dy, -s * dx + c * dy
        a, b = self.a[:, None], self.b[:, None]
        q = np.sqrt((x / a) ** 2 + (y / b) ** 2) + 1e-12
        grad = np.sqrt((x / a**2) ** 2 + (y / b**2) ** 2) / q + 1e-12
        return (q - 1.0) / grad


_EYE5 = np.eye(5)


def fit_ellipses(pts: Array, weights: Array) -> Ellipses:
    """Least-squares conics through point sets ``["C", "N", 2]`` with weights ``["C", "N"]``.

    Each set is centred and scaled first, then ``A x² + B xy + C y² + D x + E y = 1`` is solved
    by its 5 × 5 normal equations, all sets in one batched solve. For closed rims with sub-pixel
    noise the algebraic fit's bias is O(σ²/r), far below the noise; sets that give no real
    ellipse come back with ``valid`` False.
    """
    # Sums over the points are products with the weights (matmul), not np.add.reduce over the
    # middle axis of small 3-D arrays, which is ~3x slower there (this runs in every measuring
    # pass); the same numbers up to rounding.
    C, P = weights.shape
    w = weights.astype(float)
    wr = w[:, None, :]  # [C, 1, N]
    count = np.add.reduce(w, axis=1)
    n = np.maximum(count, 1.0)
    mean = np.matmul(wr, pts)[:, 0, :] / n[:, None]
    d = pts - mean[:, None, :]
    scale = np.sqrt(np.add.reduce(np.matmul(wr, d * d)[:, 0, :], axis=1) / n) + 1e-12
    inv = 1.0 / scale[:, None]
    x, y = d[..., 0] * inv, d[..., 1] * inv
    M = np.empty((C, 5, P))  # the conic's monomials per point, [C, 5, N]
    np.multiply(x, x, out=M[:, 0])
    np.multiply(x, y, out=M[:, 1])
    np.multiply(y, y, out=M[:, 2])
    M[:, 3] = x
    M[:, 4] = y
    Mw = M * wr
    N = np.matmul(Mw, M.transpose(0, 2, 1)) + 1e-12 * _EYE5
    rhs = np.add.reduce(Mw, axis=2)
    valid = count >= 6
    try:
        p = np.linalg.solve(N, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        p = np.zeros((len(pts), 5))
        valid = np.zeros(len(pts), dtype=bool)
    A, B, Cc, D, E = p.T
    det = 4.0 * A * Cc - B * B
    valid &= det > 1e-12
    det = np.where(valid, det, 1.0)
    x0 = (B * E - 2.0 * Cc * D) / det
    y0 = (B * D - 2.0 * A * E) / det
    k = 1.0 - 0.5 * (
        D * x0 + E * y0
    )  # (p - c)^T Q (p - c) = k at the rim, Q = [[A, B/2], [B/2, C]]
    # Eigenvalues of Q in closed form; the smaller one belongs to the major axis.
    mid, rad = 0.5 * (A + Cc), np.hypot(0.5 * (A - Cc), 0.5 * B)
    lam_small, lam_big = mid - rad, mid + rad
    valid &= (lam_small > 0) & (k > 0)
    lam_small = np.where(valid, lam_small, 1.0)
    lam_big = np.where(valid, lam_big, 1.0)
    k = np.where(valid, k, 1.0)
    a = np.sqrt(k / lam_small) * scale
    b = np.sqrt(k / lam_big) * scale
    angle = 0.5 * np.arctan2(B, A - Cc) + 0.5 * np.pi  # atan2 gives the minor axis' direction
    centre = mean
    centre[:, 0] += x0 * scale
    centre[:, 1] += y0 * scale
    return Ellipses(centre, a, b, angle, valid)


def fit_ellipse(pts: Array) -> Ellipse | None:
    """The least-squares ellipse through ``["N", 2]`` points (:func:`fit_ellipses` for one set)."""
    if pts.shape[0] < 6:
        return None
    e = fit_ellipses(pts[None].astype(float), np.ones((1, pts.shape[0])))
    return e[0] if bool(e.ok[0]) else None


def rim_points(pm: ProjectedMark, radius_mm: float, n: int = _RIM_SAMPLES) -> Array:
    """``n`` points ``["n", 3]`` (camera frame) evenly spaced on the rim of the mark's circle."""
    return rims(pm.p_cf[None], pm.n_cf[None], radius_mm, n)[0]


def rims(p_cf: Array, n_cf: Array, radius_mm: float | Array, n: int = _RIM_SAMPLES) -> Array:
    """:func:`rim_points` of marks at ``p_cf`` ``["M", 3]`` with unit normals ``n_cf`` and radii
    ``radius_mm`` (one for all, or ``["M"]``): ``["M", "n", 3]``."""
    nx, ny, nz = n_cf[:, 0:1], n_cf[:, 1:2], n_cf[:, 2:3]
    zero = np.zeros_like(nx)
    # e1 = n × (x or y axis), e2 = n × e1: an orthonormal basis of the mark's plane.
    e1 = np.where(
        np.abs(nx) < 0.9,
        np.concatenate([zero, nz, -ny], axis=1),
        np.concatenate([-nz, zero, nx], axis=1),
    )
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.concatenate(  # n × e1
        [ny * e1[:, 2:3] - nz * e1[:, 1:2], nz * e1[:, 0:1] - nx * e1[:, 2:3],
         nx * e1[:, 1:2] - ny * e1[:, 0:1]],
        axis=1,
    )
    cs = _cos_sin(n)
    r = np.broadcast_to(np.asarray(radius_mm, dtype=float), (p_cf.shape[0],))[:, None, None]
    return p_cf[:, None, :] + r * (
        cs[None, :, :1] * e1[:, None, :] + cs[None, :, 1:] * e2[:, None, :]
    )


@dataclass(frozen=True)
class MarkPrediction:
    """One mark as the recipe and a pose predict it in one image."""

    mark: ProjectedMark
    ellipse: Ellipse  # the imaged rim, as the detector would fit it
    correction: Array  # [2] image of the circle centre minus the ellipse centre
    max_shift_px: float  # how far the mark may move within the recipe's tolerances
    radius_range: tuple[float, float]  # accepted sqrt(a·b), px
    ratio_range: tuple[float, float]  # accepted minor/major axis ratio
    facing: bool  # the mark's front faces the camera
    dark: bool = True  # the mark is darker than its surroundings (its polarity)
    diameter_mm: float = 0.0  # the mark's own diameter

    @property
    def uv(self) -> Array:
        return self.mark.uv


def displacement_mm(recipe: RecipeConfig, reach: float = 1.0) -> Array:
    """Bound ``["M"]`` on each mark's 3D motion for any allowed part displacement.

    The allowed displacement is a rigid motion bounded at the part, not at the part frame's
    origin: a rotation of at most ``reach · max_offset_deg`` about the marks' centroid ``c``
    followed by a translation of at most ``reach · max_offset_mm``. Mark ``i`` then stays within
    ``reach · max_offset_mm + 2 |p_i − c| sin(reach · max_offset_deg / 2)`` of where the prior
    pose puts it; ``p_i − c`` is the same in every part frame, so the bound (and every window
    and size range built from it) does not depend on where the part frame is.
    """
    tol = recipe.tolerances
    P = recipe.mark_positions()
    lever = np.linalg.norm(P - P.mean(axis=0), axis=1)
    return reach * tol.max_offset_mm + 2.0 * lever * np.sin(
        np.deg2rad(reach * tol.max_offset_deg) / 2.0
    )


# Directions in which a mark's displacement is tried: the 6 axes and the 8 cube diagonals.
_DIRS = np.concatenate(
    [
        np.eye(3),
        -np.eye(3),
        np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3) / np.sqrt(3),
    ]
)


_PREDICTIONS: IdentityCache[list[MarkPrediction]] = IdentityCache(32)


def predict_marks_cached(
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf: Array,
    size_tolerance: float = 0.15,
    shape_slack_deg: float = 8.0,
    reach: float = 1.0,
) -> list[MarkPrediction]:
    """:func:`predict_marks` of the sighted marks, remembered for recent (camera, recipe, pose).

    Window mode predicts from the same prior at every trigger; this saves ~0.5 ms per image. The
    entry holds the camera and recipe objects themselves and is used only for those very objects
    (both are frozen), so a changed station or recipe never gets a stale prediction.
    """
    T = np.ascontiguousarray(T_rf_from_pf, dtype=float)
    extra = (T.tobytes(), float(size_tolerance), float(shape_slack_deg), float(reach))
    return _PREDICTIONS.get(
        (cam, recipe), extra,
        lambda: _predict_reposed(cam, recipe, T, extra, size_tolerance, shape_slack_deg, reach),
    )


def predict_marks_cached_many(
    cams: list[ViewCamera],
    recipe: RecipeConfig,
    T_rf_from_pf: Array,
    size_tolerance: float = 0.15,
    shape_slack_deg: float = 8.0,
    reach: float = 1.0,
) -> list[list[MarkPrediction]]:
    """:func:`predict_marks_cached` for several cameras at one pose: the cameras whose
    prediction there is not remembered (nor that of their camera place) are predicted together
    (:func:`predict_marks_many`, one ellipse fit for all) and remembered as it does."""
    T = np.ascontiguousarray(T_rf_from_pf, dtype=float)
    extra = (T.tobytes(), float(size_tolerance), float(shape_slack_deg), float(reach))
    found: list[list[MarkPrediction] | None] = []
    for cam in cams:
        preds = _PREDICTIONS.peek((cam, recipe), extra)
        if preds is None:
            place = _PLACES.peek((recipe,), (_place_key(cam), extra))
            if place is not None:  # that place's own camera, or one to re-pose it for
                preds = predict_marks_cached(cam, recipe, T, size_tolerance, shape_slack_deg,
                                             reach)
        found.append(preds)
    missing = [k for k, f in enumerate(found) if f is None]
    if missing:
        made = predict_marks_many(
            [(cams[k], sighted_marks(recipe, cams[k].view, cams[k].camera_id)) for k in missing],
            recipe, T, size_tolerance, shape_slack_deg, reach)
        for k, preds in zip(missing, made, strict=True):
            _remember(cams[k], recipe, T, extra, preds, reach)
            found[k] = preds
    return [f for f in found if f is not None]


def _remember(cam: ViewCamera, recipe: RecipeConfig, T: Array,
              extra: tuple[bytes, float, float, float], preds: list[MarkPrediction],
              reach: float) -> None:
    """Keep predictions made elsewhere as :func:`predict_marks_cached` keeps its own."""

    def place() -> _Place:
        return _place_of(cam, recipe, T, preds, reach)

    def made() -> list[MarkPrediction]:
        return preds

    _PLACES.get((recipe,), (_place_key(cam), extra), place)
    _PREDICTIONS.get((cam, recipe), extra, made)


@dataclass(frozen=True)
class _Place:
    """The first prediction made at a camera place, with what re-posing it needs."""

    cam: ViewCamera
    preds: list[MarkPrediction]
    p_rf: Array  # [M, 3] the predicted marks at the prior pose, in RF
    p_cf: Array  # [M, 3] the same in the first camera
    limit_mm: Array  # [M] how far each may move relative to the camera to be re-posed


# The first prediction of each camera place (view, camera, rig; the lens by value), to re-pose.
_PLACES: IdentityCache[_Place] = IdentityCache(64)
#: how far (a share of the recipe's displacement bound) the marks may have moved relative to a
#: place's first camera for its prediction to be re-posed instead of computed anew
REPOSE_SHARE = 0.01


def _place_key(cam: ViewCamera) -> tuple[object, ...]:
    """A camera place: its view, camera, rig and lens (by value), whatever its pose."""
    return (cam.view, cam.camera_id, cam.rig_id, cam.rig_position, cam.model)


def _place(cam: ViewCamera, recipe: RecipeConfig, T: Array, size_tolerance: float,
           shape_slack_deg: float, reach: float) -> _Place:
    preds = predict_marks(cam, recipe, T, size_tolerance, shape_slack_deg, reach=reach)
    return _place_of(cam, recipe, T, preds, reach)


def _place_of(cam: ViewCamera, recipe: RecipeConfig, T: Array, preds: list[MarkPrediction],
              reach: float) -> _Place:
    index = {m.id: k for k, m in enumerate(recipe.marks)}
    ks = [index[p.mark.mark_id] for p in preds]
    p_rf = recipe.mark_positions()[ks] @ T[:3, :3].T + T[:3, 3]
    p_cf = np.array([p.mark.p_cf for p in preds]).reshape(-1, 3)
    return _Place(cam, preds, p_rf, p_cf, REPOSE_SHARE * displacement_mm(recipe, reach)[ks])


def _predict_reposed(
    cam: ViewCamera,
    recipe: RecipeConfig,
    T: Array,
    extra: tuple[bytes, float, float, float],
    size_tolerance: float,
    shape_slack_deg: float,
    reach: float,
) -> list[MarkPrediction]:
    """:func:`predict_marks`, or the prediction of the same camera place re-posed.

    A robot-mounted view with the robot's actual flange pose brings a new camera pose, and so a
    new :class:`ViewCamera`, at every trigger, a few hundredths of a mm from the taught one. The
    windows then need not be predicted again (rim sampling, ellipse fits, the tolerance's
    projections: ~1 ms per image): each mark is projected through the new pose and its
    prediction moved by the difference of the centres; shapes, sizes and reach stay. That is
    exact to first order in the motion, and used only while every mark moved by at most
    :data:`REPOSE_SHARE` of its displacement bound (1-2 mm for ±100 mm), where the second-order
    change stays well inside the windows' margin (``window_extra_px``, 6 px: the lab station's
    reach of ~575 px changes by 0.6 px for 0.5 mm and 0.02°, by ~0.02 px for a robot's 0.02 mm
    repeatability; tests/mvpose_core/test_repose.py); else the prediction is computed anew.
    """
    place = _PLACES.get((recipe,), (_place_key(cam), extra), lambda: _place(
        cam, recipe, T, size_tolerance, shape_slack_deg, reach))
    if place.cam is cam or not place.preds:
        return place.preds
    R, t = cam.T_rf_from_cf[:3, :3], cam.T_rf_from_cf[:3, 3]
    p_cf = (place.p_rf - t) @ R  # Rᵀ (p - t), row by row
    moved = np.sqrt(np.add.reduce((p_cf - place.p_cf) ** 2, axis=1))
    if not (np.all(p_cf[:, 2] > 1.0) and np.all(moved <= place.limit_mm)):
        return predict_marks(cam, recipe, T, size_tolerance, shape_slack_deg, reach=reach)
    R_cf_from_first = R.T @ place.cam.T_rf_from_cf[:3, :3]
    uv = cam.model.project(p_cf)
    out = []
    for k, p in enumerate(place.preds):
        du = uv[k] - p.mark.uv
        mark = ProjectedMark(mark_id=p.mark.mark_id, uv=uv[k], depth_mm=float(p_cf[k, 2]),
                             p_cf=p_cf[k], n_cf=R_cf_from_first @ p.mark.n_cf)
        ell = Ellipse(centre=p.ellipse.centre + du, a=p.ellipse.a, b=p.ellipse.b,
                      angle=p.ellipse.angle)
        out.append(MarkPrediction(
            mark=mark, ellipse=ell, correction=p.correction, max_shift_px=p.max_shift_px,
            radius_range=p.radius_range, ratio_range=p.ratio_range, facing=p.facing,
            dark=p.dark, diameter_mm=p.diameter_mm))
    return out


def predict_marks(
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf: Array,
    size_tolerance: float = 0.15,
    shape_slack_deg: float = 8.0,
    mark_ids: list[str] | None = None,
    reach: float = 1.0,
) -> list[MarkPrediction]:
    """Predict every sighted mark (or ``mark_ids``) of the recipe in ``cam`` at ``T_rf_from_pf``.

    Windows, sizes and shapes allow for any part offset within ``reach`` times the recipe's
    tolerances (``max_offset_mm``, ``max_offset_deg``).
    """
    if mark_ids is None:
        ids = sighted_marks(recipe, cam.view, cam.camera_id)
    else:
        ids = [m.id for m in recipe.marks if m.id in mark_ids]
    return predict_marks_many([(cam, ids)], recipe, T_rf_from_pf, size_tolerance,
                              shape_slack_deg, reach)[0]


def predict_marks_many(
    cameras: list[tuple[ViewCamera, list[str]]],
    recipe: RecipeConfig,
    T_rf_from_pf: Array,
    size_tolerance: float = 0.15,
    shape_slack_deg: float = 8.0,
    reach: float = 1.0,
) -> list[list[MarkPrediction]]:
    """:func:`predict_marks` of the marks ``ids`` for each (camera, ids), in their order.

    Batched over the marks of every camera: per camera one transform and one projection (its
    centres, rims and displaced centres together), then one ellipse fit and the ranges for
    all; each camera's predictions are those :func:`predict_marks` gives it alone (a part's
    pose from its first blobs is new at every trigger, and its windows are predicted in every
    camera at once).
    """
    positions, normals = _mark_geometry(recipe)
    diameters, darks = _mark_looks(recipe)
    index = {m.id: k for k, m in enumerate(recipe.marks)}
    cams = [(cam, [index[i] for i in ids]) for cam, ids in cameras]
    used = [(cam, ks) for cam, ks in cams if ks]
    if not used:
        return [[] for _ in cameras]
    T_pf = np.asarray(T_rf_from_pf, dtype=float)
    ks_all = [k for _, ks in used for k in ks]
    posed = []
    for cam, ks in used:
        T = compose(invert(cam.T_rf_from_cf), T_pf)
        R, t = T[:3, :3], T[:3, 3]
        posed.append((positions[ks] @ R.T + t, normals[ks] @ R.T))
    p_cf = np.concatenate([p for p, _ in posed])
    n_cf = np.concatenate([n for _, n in posed])
    z = p_cf[:, 2]
    in_front = z > 1.0
    diam = diameters[ks_all]
    rim = rims(p_cf, n_cf, diam / 2.0)  # [M, n, 3]
    rim[~in_front] = [0.0, 0.0, 1.0]  # keeps the projection finite; such marks are not used
    D = displacement_mm(recipe, reach)[ks_all]
    moved = p_cf[:, None, :] + D[:, None, None] * _DIRS[None]  # [M, 14, 3]
    ahead = moved[..., 2] > 0.2 * np.maximum(z, 1.0)[:, None]
    moved[..., 2] = np.where(ahead, moved[..., 2], 1.0)
    # per camera one projection of its centres, rims and displaced centres
    M_all, n_rim, n_dir = len(ks_all), rim.shape[1], _DIRS.shape[0]
    uv = np.empty((M_all, 2))
    rim_uv = np.empty((M_all, n_rim, 2))
    moved_uv = np.empty((M_all, n_dir, 2))
    first = 0
    for cam, ks in used:
        m = slice(first, first + len(ks))
        M = len(ks)
        uv_all = cam.model.project(
            np.concatenate([p_cf[m], rim[m].reshape(-1, 3), moved[m].reshape(-1, 3)]))
        uv[m] = uv_all[:M]
        rim_uv[m] = uv_all[M : M + M * n_rim].reshape(M, n_rim, 2)
        moved_uv[m] = uv_all[M + M * n_rim :].reshape(M, n_dir, 2)
        first += M
    moved_uv -= uv[:, None]
    ells = fit_ellipses(rim_uv, np.ones(rim_uv.shape[:2]))
    shift_all = np.sqrt(np.einsum("mdi,mdi->md", moved_uv, moved_uv))
    shift = np.where(ahead.all(axis=1), shift_all.max(axis=1), 1e9)
    view = p_cf / np.linalg.norm(p_cf, axis=1, keepdims=True)
    tilt = np.degrees(np.arccos(np.clip(np.abs(np.einsum("mi,mi->m", n_cf, view)), 0.0, 1.0)))
    spread = reach * recipe.tolerances.max_offset_deg + shape_slack_deg
    facing = in_front & ells.ok & (np.einsum("mi,mi->m", n_cf, p_cf) < 0.0)
    # a mark that does not face the camera gets a unit circle at its centre (never searched)
    centre = np.where(facing[:, None], ells.centre, uv)
    a = np.where(facing, ells.a, 1.0)
    b = np.where(facing, ells.b, 1.0)
    angle = np.where(facing, ells.angle, 0.0)
    r = np.sqrt(a * b)
    near, far = np.maximum(z - D, 0.2 * z), z + D
    r_lo = r * z / far * (1.0 - size_tolerance)
    r_hi = r * z / near * (1.0 + size_tolerance)
    ratio_lo = np.cos(np.deg2rad(np.minimum(tilt + spread, 85.0))) * (1.0 - size_tolerance)
    ratio_hi = np.where(
        tilt - spread > 0,
        np.minimum(1.0, np.cos(np.deg2rad(np.maximum(tilt - spread, 0.0)))
                   * (1.0 + size_tolerance)),
        1.0,
    )
    corr = uv - centre
    ids_all = [recipe.marks[k].id for k in ks_all]
    preds: list[MarkPrediction] = []
    for k, (mid, zk, ak, bk, gk, sk, lo, hi, qlo, qhi, fk, dk, dm) in enumerate(zip(
        ids_all, z.tolist(), a.tolist(), b.tolist(), angle.tolist(), shift.tolist(),
        r_lo.tolist(), r_hi.tolist(), ratio_lo.tolist(), ratio_hi.tolist(), facing.tolist(),
        darks[ks_all].tolist(), diam.tolist(), strict=True,
    )):
        preds.append(
            MarkPrediction(
                mark=ProjectedMark(mark_id=mid, uv=uv[k], depth_mm=zk, p_cf=p_cf[k],
                                   n_cf=n_cf[k]),
                ellipse=Ellipse(centre=centre[k], a=ak, b=bk, angle=gk),
                correction=corr[k],
                max_shift_px=sk,
                radius_range=(lo, hi),
                ratio_range=(qlo, qhi),
                facing=fk,
                dark=dk,
                diameter_mm=dm,
            )
        )
    out: list[list[MarkPrediction]] = []
    first = 0
    for _, ks in cams:
        out.append(preds[first : first + len(ks)])
        first += len(ks)
    return out


_GEOMETRY: IdentityCache[tuple[Array, Array]] = IdentityCache(16)


def _mark_geometry(recipe: RecipeConfig) -> tuple[Array, Array]:
    """The recipe's mark positions ``["M", 3]`` and unit normals (part frame), read-only."""

    def make() -> tuple[Array, Array]:
        p = np.array([m.position for m in recipe.marks], dtype=float)
        n = np.array([m.normal for m in recipe.marks], dtype=float)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        p.flags.writeable = n.flags.writeable = False
        return p, n

    return _GEOMETRY.get((recipe,), None, make)


_LOOKS: IdentityCache[tuple[Array, Array]] = IdentityCache(16)


def _mark_looks(recipe: RecipeConfig) -> tuple[Array, Array]:
    """Each mark's diameter ``["M"]`` (mm) and polarity (dark on light), read-only."""

    def make() -> tuple[Array, Array]:
        d, dark = recipe.mark_diameters(), recipe.mark_dark()
        d.flags.writeable = dark.flags.writeable = False
        return d, dark

    return _LOOKS.get((recipe,), None, make)
