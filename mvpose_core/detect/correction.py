"""The perspective correction of mark centres at a pose: how far each ellipse's centre lies from
the image of its circle's centre, for every camera of a trigger at once.

The image of a circle is (up to lens distortion) an ellipse whose centre is not the image of the
circle's centre. The correction is computed as the detector measures: the circle's rim is sampled
in 3D at the pose, projected through the lens, and an ellipse fitted to it
(:func:`mvpose_core.detect.geometry.fit_ellipses`); the correction is the circle centre's image
minus that ellipse's centre. :data:`CORRECTION_RIM_SAMPLES` rim points suffice: the projected
rim is an ellipse to far below a pixel's 1e-10 even under strong distortion, so its least-squares
fit does not depend on how densely it is sampled (16 points against the 72 of the window
prediction: the same correction to 1e-12 px on every station in deploy/stations and the test
stations of tests/mvpose_core/real_stations.py; tests/mvpose_core/test_correction.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.detect.ellipse import fit_ellipses, rims
from mvpose_core.detect.marks import mark_geometry
from mvpose_core.detect.types import MarkDetection
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

#: rim points per mark for the correction (tests/mvpose_core/test_correction.py: the same
#: correction as with 72 points to 1e-12 px on every station we have)
CORRECTION_RIM_SAMPLES = 16


def perspective_correction(
    cam: ViewCamera, recipe: RecipeConfig, T_rf_from_pf: Array, mark_ids: list[str]
) -> dict[str, Array]:
    """Per mark, the vector (px) from the imaged ellipse's centre to the circle centre's image
    (:func:`perspective_corrections` for one camera)."""
    return perspective_corrections([(cam, mark_ids)], recipe, T_rf_from_pf)[0]


def perspective_corrections(
    cameras: Sequence[tuple[ViewCamera, Sequence[str]]], recipe: RecipeConfig,
    T_rf_from_pf: Array, rim_samples: int = CORRECTION_RIM_SAMPLES,
) -> list[dict[str, Array]]:
    """:func:`perspective_correction` for each (camera, mark ids): marks behind a camera or not
    facing it, and rims that fit no ellipse, have none.

    This runs once per trigger at the estimated pose, for every camera that saw marks: the
    marks posed once in RF, one projection of every centre and rim per distinct lens, and one
    ellipse fit for all.
    """
    positions, normals = mark_geometry(recipe)
    index = _mark_index(recipe)
    T = np.asarray(T_rf_from_pf, dtype=float)
    # Every (camera, mark) as a row: its mark, its camera's pose; one transform for all rows.
    ks: list[int] = []
    ci: list[int] = []
    for c, (_, ids) in enumerate(cameras):
        row = [index[i] for i in ids if i in index]
        ks += row
        ci += [c] * len(row)
    if not ks:
        return [{} for _ in cameras]
    T_cf = np.array([cam.T_rf_from_cf for cam, _ in cameras])[ci]  # [F, 4, 4] per row
    R_rf_from_cf, t_rf_from_cf = T_cf[:, :3, :3], T_cf[:, :3, 3]
    # p_cf = R_cfᵀ (R p + t − t_cf), n_cf = R_cfᵀ R n, row by row
    p_cf = np.einsum("nji,nj->ni", R_rf_from_cf, positions[ks] @ T[:3, :3].T + T[:3, 3]
                     - t_rf_from_cf)
    n_cf = np.einsum("nji,nj->ni", R_rf_from_cf, normals[ks] @ T[:3, :3].T)
    facing = (p_cf[:, 2] > 1.0) & (np.einsum("mi,mi->m", n_cf, p_cf) < 0.0)
    keep = facing.tolist()
    marks = recipe.marks
    chosen: list[list[str]] = [[] for _ in cameras]  # per camera: its facing marks, in order
    for k, c, f in zip(ks, ci, keep, strict=True):
        if f:
            chosen[c].append(marks[k].id)
    if not any(keep):
        return [{} for _ in cameras]
    p_cf, n_cf = p_cf[facing], n_cf[facing]
    radii = _radii(recipe)[np.asarray(ks)[facing]]
    rim = rims(p_cf, n_cf, radii, rim_samples)
    pts = np.concatenate([p_cf[:, None, :], rim], axis=1)  # [F, 1 + n, 3]: centre, then rim
    models = [cameras[c][0].model for c, f in zip(ci, keep, strict=True) if f]
    first = models[0]  # one lens (the usual station): one projection
    if all(m is first or m == first for m in models):
        uv = first.project(pts.reshape(-1, 3)).reshape(pts.shape[0], -1, 2)
    else:  # one projection per run of rows with the same lens (a camera's rows are one run)
        uv = np.empty(pts.shape[:2] + (2,))
        cuts = [j for j in range(1, len(models)) if models[j] is not models[j - 1]]
        for a, b in zip([0, *cuts], [*cuts, len(models)], strict=True):
            uv[a:b] = models[a].project(pts[a:b].reshape(-1, 3)).reshape(b - a, -1, 2)
    ells = fit_ellipses(uv[:, 1:], np.ones(uv.shape[:1] + (rim_samples,)))
    corr = uv[:, 0] - ells.centre
    ok = ells.ok.tolist()
    out: list[dict[str, Array]] = []
    k = 0
    for ids in chosen:
        out.append({mid: corr[k + j] for j, mid in enumerate(ids) if ok[k + j]})
        k += len(ids)
    return out


_INDEX: IdentityCache[tuple[dict[str, int], Array]] = IdentityCache(16)


def _mark_index(recipe: RecipeConfig) -> dict[str, int]:
    """Each mark id's row in the recipe's mark arrays."""
    return _INDEX.get((recipe,), None, lambda: _index_and_radii(recipe))[0]


def _radii(recipe: RecipeConfig) -> Array:
    """Each mark's radius ``["M"]`` (mm), read-only."""
    return _INDEX.get((recipe,), None, lambda: _index_and_radii(recipe))[1]


def _index_and_radii(recipe: RecipeConfig) -> tuple[dict[str, int], Array]:
    r = recipe.mark_diameters() / 2.0
    r.flags.writeable = False
    return {m.id: k for k, m in enumerate(recipe.marks)}, r


Groups = Sequence[tuple[ViewCamera, Sequence[MarkDetection]]]


def corrections_at(
    groups: Groups, recipe: RecipeConfig, T_rf_from_pf: Array
) -> tuple[list[dict[str, Array]], float]:
    """Each camera's corrections at ``T_rf_from_pf`` for its found detections (those with a
    fitted ellipse), and the largest change (px) of any against the one its detection carried
    (none: 0 px). Nothing is rebuilt: :func:`corrected` applies them when they matter."""
    usable = [[d for d in dets if d.found and d.uv_ellipse is not None] for _, dets in groups]
    corrs = perspective_corrections(
        [(cam, [d.mark_id for d in ds]) for (cam, _), ds in zip(groups, usable, strict=True)],
        recipe, T_rf_from_pf,
    )
    new: list[Array] = []
    old: list[Array] = []
    for ds, corr in zip(usable, corrs, strict=True):
        for d in ds:
            c = corr.get(d.mark_id)
            if c is not None:
                new.append(c)
                old.append(d.correction if d.correction is not None else _ZERO2)
    if not new:
        return corrs, 0.0
    step = np.array(new) - np.array(old, dtype=float)
    return corrs, float(np.sqrt(np.einsum("ni,ni->n", step, step).max()))


_ZERO2 = np.zeros(2)


def corrected(
    groups: Groups, corrections: Sequence[dict[str, Array]]
) -> list[list[MarkDetection]]:
    """Each camera's detections with the ``corrections`` of :func:`corrections_at` applied:
    ``uv = uv_ellipse + correction`` for the found marks that have one, the others as given."""
    out = []
    for (_, dets), corr in zip(groups, corrections, strict=True):
        moved = []
        for d in dets:
            c = corr.get(d.mark_id)
            if not d.found or d.uv_ellipse is None or c is None:
                moved.append(d)
            else:
                moved.append(replace(d, uv=d.uv_ellipse + c, correction=np.array(c, dtype=float)))
        out.append(moved)
    return out
