"""Synthetic measurements with known truth: part displacements and noisy mark observations."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mvpose_core.camera import check_in_front
from mvpose_core.estimate import Observation
from mvpose_core.scene import project_recipe_marks, view_cameras
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.transforms import Array, check_transform, rotvec_to_matrix, xyzwpr_to_matrix


def random_displacement(rng: np.random.Generator, max_mm: float, max_deg: float) -> Array:
    """A random part displacement ``T_pf0_from_pf`` (4x4), uniform per axis.

    X, Y, Z uniform in ±``max_mm`` and W, P, R uniform in ±``max_deg``, about the part's own
    origin and axes — what a part lying a little off its taught place looks like. The part
    then sits at ``T_rf_from_pf = T_rf_from_pf0 @ displacement``.
    """
    if not (max_mm >= 0 and max_deg >= 0):
        raise ValueError(f"max_mm and max_deg must be ≥ 0, got {max_mm}, {max_deg}")
    xyz = rng.uniform(-max_mm, max_mm, 3)
    wpr = rng.uniform(-max_deg, max_deg, 3)
    return xyzwpr_to_matrix([*xyz, *wpr])


#: the directions a displaced part moves in for the benchmarks and tests (translation, axis)
T_DIR: Array = np.array([0.7, -0.6, 0.4])
R_DIR: Array = np.array([0.5, -0.4, 0.75])


def displaced(recipe: RecipeConfig, share: float, t_dir: Array = T_DIR,
              r_dir: Array = R_DIR) -> Array:
    """The recipe's reference pose moved by ``share`` of its tolerance: a rotation of
    ``share·max_offset_deg`` about the marks' centroid (axis ``r_dir``), then a translation of
    ``share·max_offset_mm`` along ``t_dir``, in the part frame (a negative share: the other
    way)."""
    tol = recipe.tolerances
    c = np.asarray(recipe.mark_centroid(), dtype=float)
    R = rotvec_to_matrix(np.deg2rad(share * tol.max_offset_deg) * r_dir / np.linalg.norm(r_dir))
    D = np.eye(4)
    D[:3, :3] = R
    D[:3, 3] = share * tol.max_offset_mm * t_dir / np.linalg.norm(t_dir) + c - R @ c
    return np.asarray(recipe.T_rf_from_pf0.matrix @ D)


def synthetic_observations(
    station: StationConfig,
    recipe: RecipeConfig,
    T_rf_from_pf: np.ndarray,
    rng: np.random.Generator,
    sigma_px: float,
    flange_poses: Mapping[int, np.ndarray] | None = None,
    *,
    require_in_image: bool = True,
) -> list[Observation]:
    """Every sighting of the recipe, projected for a part at ``T_rf_from_pf``, plus N(0, σ²) noise.

    ``flange_poses`` are the robot's actual flange poses (the truth), as in
    :func:`mvpose_core.scene.view_cameras`. A sighted mark behind its camera raises
    ``ValueError``; one outside the image raises too unless ``require_in_image`` is False
    (numerical studies may look past the image border).
    """
    T = check_transform(T_rf_from_pf, "T_rf_from_pf")
    if not (np.isfinite(sigma_px) and sigma_px >= 0):
        raise ValueError(f"sigma_px must be ≥ 0, got {sigma_px}")
    out: list[Observation] = []
    for cam in view_cameras(station, flange_poses):
        marks = project_recipe_marks(cam, recipe, T)
        for pm in marks:
            check_in_front(pm.p_cf[None], f"mark {pm.mark_id} in camera {cam.key}")
            if require_in_image and not cam.model.in_image(pm.uv[None])[0]:
                raise ValueError(
                    f"mark {pm.mark_id} falls outside camera {cam.key} at "
                    f"({pm.uv[0]:.0f}, {pm.uv[1]:.0f}) px"
                )
        noise = (
            rng.normal(0.0, sigma_px, (len(marks), 2))
            if sigma_px > 0
            else np.zeros((len(marks), 2))
        )
        out.extend(
            Observation(cam.view, cam.camera_id, pm.mark_id, pm.uv + noise[i])
            for i, pm in enumerate(marks)
        )
    return out
