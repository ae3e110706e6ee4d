"""What a recipe and a camera give once: the marks' positions, normals, sizes and polarities,
how far each may move within a share of the tolerances, and a camera's inverse pose.

The predictions (geometry.py) and the corrections (correction.py) need these at every trigger,
and a part's pose from its blobs is new at every trigger while its recipe and cameras are not:
each is made once and remembered by object identity (mvpose_core/cache.py), read-only.
"""

from __future__ import annotations

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, invert


def displacement_mm(recipe: RecipeConfig, reach: float = 1.0) -> Array:
    """Bound ``["M"]`` on each mark's 3D motion for any allowed part displacement (read-only,
    remembered per recipe and reach).

    The allowed displacement is a rigid motion bounded at the part, not at the part frame's
    origin: a rotation of at most ``reach · max_offset_deg`` about the marks' centroid ``c``
    followed by a translation of at most ``reach · max_offset_mm``. Mark ``i`` then stays within
    ``reach · max_offset_mm + 2 |p_i − c| sin(reach · max_offset_deg / 2)`` of where the prior
    pose puts it; ``p_i − c`` is the same in every part frame, so the bound (and every window
    and size range built from it) does not depend on where the part frame is.
    """

    def make() -> Array:
        tol = recipe.tolerances
        P = recipe.mark_positions()
        lever = np.linalg.norm(P - P.mean(axis=0), axis=1)
        D = reach * tol.max_offset_mm + 2.0 * lever * np.sin(
            np.deg2rad(reach * tol.max_offset_deg) / 2.0
        )
        D.flags.writeable = False
        return D

    return _DISPLACEMENT.get((recipe,), float(reach), make)


#: the displacement bounds of recent (recipe, reach), read-only: a part's pose from its blobs
#: is new at every trigger, its recipe and reach are not
_DISPLACEMENT: IdentityCache[Array] = IdentityCache(16)
_CF_FROM_RF: IdentityCache[Array] = IdentityCache(64)


def cf_from_rf(cam: ViewCamera) -> Array:
    """``T_cf_from_rf`` of a camera (remembered per camera object, read-only)."""

    def make() -> Array:
        T = invert(cam.T_rf_from_cf)
        T.flags.writeable = False
        return T

    return _CF_FROM_RF.get((cam,), None, make)


_GEOMETRY: IdentityCache[tuple[Array, Array]] = IdentityCache(16)


def mark_geometry(recipe: RecipeConfig) -> tuple[Array, Array]:
    """The recipe's mark positions ``["M", 3]`` and unit normals (part frame), read-only."""

    def make() -> tuple[Array, Array]:
        p = np.array([m.position for m in recipe.marks], dtype=float)
        n = np.array([m.normal for m in recipe.marks], dtype=float)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        p.flags.writeable = n.flags.writeable = False
        return p, n

    return _GEOMETRY.get((recipe,), None, make)


_LOOKS: IdentityCache[tuple[Array, Array]] = IdentityCache(16)


def mark_looks(recipe: RecipeConfig) -> tuple[Array, Array]:
    """Each mark's diameter ``["M"]`` (mm) and polarity (dark on light), read-only."""

    def make() -> tuple[Array, Array]:
        d, dark = recipe.mark_diameters(), recipe.mark_dark()
        d.flags.writeable = dark.flags.writeable = False
        return d, dark

    return _LOOKS.get((recipe,), None, make)
