"""What the recipe predicts for each mark in an image: its ellipse, window and centre correction.

The image of a circle is (up to lens distortion) an ellipse whose centre is not the image of the
circle's centre. Both the expected ellipse and the correction come from the same computation: the
circle's rim is sampled in 3D at the given pose, projected through the lens, and an ellipse is
fitted to it exactly as the detector fits one to edge points
(:func:`mvpose_core.detect.ellipse.fit_ellipses`). The
correction alone, at the estimated pose, is :mod:`mvpose_core.detect.correction`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.detect.ellipse import Ellipse, fit_ellipses, rims
from mvpose_core.detect.marks import cf_from_rf, displacement_mm, mark_geometry, mark_looks
from mvpose_core.scene import ProjectedMark, ViewCamera, sighted_marks
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, compose


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
    positions, normals = mark_geometry(recipe)
    diameters, darks = mark_looks(recipe)
    index = {m.id: k for k, m in enumerate(recipe.marks)}
    cams = [(cam, [index[i] for i in ids]) for cam, ids in cameras]
    used = [(cam, ks) for cam, ks in cams if ks]
    if not used:
        return [[] for _ in cameras]
    T_pf = np.asarray(T_rf_from_pf, dtype=float)
    ks_all = [k for _, ks in used for k in ks]
    posed = []
    for cam, ks in used:
        T = compose(cf_from_rf(cam), T_pf)
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
