"""What the recipe predicts for each mark in an image: its ellipse, its window, its centre correction.

The image of a circle is (up to lens distortion) an ellipse whose centre is not the image of the
circle's centre. Both the expected ellipse and the correction come from the same computation: the
circle's rim is sampled in 3D at the given pose, projected through the lens, and an ellipse is fitted
to it exactly as the detector fits one to edge points (:func:`fit_ellipse`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mvpose_core.scene import ProjectedMark, ViewCamera, project_recipe_marks
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

_RIM_SAMPLES = 72


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


def fit_ellipse(pts: Array) -> Ellipse | None:
    """Direct least-squares ellipse (OpenCV ``fitEllipseDirect``) through ``["N", 2]`` points.

    Points are centred first because OpenCV takes float32: at 2000 px, float32 would cost 1e-4 px.
    """
    if pts.shape[0] < 6:
        return None
    mean = pts.mean(axis=0)
    (cx, cy), (d1, d2), ang = cv2.fitEllipseDirect((pts - mean).astype(np.float32))
    if not (np.isfinite(d1) and np.isfinite(d2) and min(d1, d2) > 0):
        return None
    angle = np.deg2rad(ang)
    a, b = 0.5 * d1, 0.5 * d2
    if b > a:
        a, b, angle = b, a, angle + 0.5 * np.pi
    return Ellipse(centre=mean + np.array([cx, cy], dtype=float), a=float(a), b=float(b), angle=float(angle))


def rim_points(pm: ProjectedMark, radius_mm: float, n: int = _RIM_SAMPLES) -> Array:
    """``n`` points ``["n", 3]`` (camera frame) evenly spaced on the rim of the mark's circle."""
    n_cf = pm.n_cf
    helper = np.array([1.0, 0.0, 0.0]) if abs(n_cf[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(n_cf, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_cf, e1)
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return pm.p_cf + radius_mm * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)


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

    @property
    def uv(self) -> Array:
        return self.mark.uv


def _displacement_mm(recipe: RecipeConfig, mark_id: str) -> float:
    """Bound on a mark's 3D motion for any part offset within the recipe's tolerances."""
    tol = recipe.tolerances
    lever = float(np.linalg.norm(recipe.marks[recipe.mark_index(mark_id)].position))
    return tol.max_offset_mm + 2.0 * lever * np.sin(np.deg2rad(tol.max_offset_deg) / 2.0)


# Directions in which a mark's displacement is tried: the 6 axes and the 8 cube diagonals.
_DIRS = np.concatenate([np.eye(3), -np.eye(3), np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3) / np.sqrt(3)])


def predict_marks(
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf: Array,
    size_tolerance: float = 0.15,
    shape_slack_deg: float = 8.0,
    mark_ids: list[str] | None = None,
) -> list[MarkPrediction]:
    """Predict every sighted mark (or ``mark_ids``) of the recipe in ``cam`` at ``T_rf_from_pf``."""
    radius_mm = recipe.mark_diameter_mm / 2.0
    out: list[MarkPrediction] = []
    for pm in project_recipe_marks(cam, recipe, T_rf_from_pf, only_sighted=mark_ids is None):
        if mark_ids is not None and pm.mark_id not in mark_ids:
            continue
        z = pm.p_cf[2]
        facing = bool(pm.n_cf @ pm.p_cf < 0.0) and z > 1.0
        if z > 1.0:
            ell = fit_ellipse(cam.model.project(rim_points(pm, radius_mm)))
        else:
            ell = None
        if ell is None:
            ell = Ellipse(centre=pm.uv, a=1.0, b=1.0, angle=0.0)
            facing = False
        D = _displacement_mm(recipe, pm.mark_id)
        moved = pm.p_cf + D * _DIRS
        moved = moved[moved[:, 2] > 0.2 * max(z, 1.0)]
        shift = float(np.max(np.linalg.norm(cam.model.project(moved) - pm.uv, axis=1))) if len(moved) else 1e9
        near, far = max(z - D, 0.2 * z), z + D
        r = ell.radius
        radius_range = (r * z / far * (1.0 - size_tolerance), r * z / near * (1.0 + size_tolerance))
        view = pm.p_cf / np.linalg.norm(pm.p_cf)
        tilt = np.degrees(np.arccos(np.clip(abs(float(pm.n_cf @ view)), 0.0, 1.0)))
        spread = recipe.tolerances.max_offset_deg + shape_slack_deg
        ratio_range = (
            float(np.cos(np.deg2rad(min(tilt + spread, 85.0)))) * (1.0 - size_tolerance),
            1.0,
        )
        if tilt - spread > 0:
            ratio_range = (ratio_range[0], float(np.cos(np.deg2rad(tilt - spread))) * (1.0 + size_tolerance))
        out.append(
            MarkPrediction(
                mark=pm,
                ellipse=ell,
                correction=pm.uv - ell.centre,
                max_shift_px=shift,
                radius_range=radius_range,
                ratio_range=(ratio_range[0], min(ratio_range[1], 1.0)),
                facing=facing,
            )
        )
    return out


def perspective_correction(
    cam: ViewCamera, recipe: RecipeConfig, T_rf_from_pf: Array, mark_ids: list[str]
) -> dict[str, Array]:
    """Per mark, the vector (px) from the imaged ellipse's centre to the image of the circle centre."""
    preds = predict_marks(cam, recipe, T_rf_from_pf, mark_ids=mark_ids)
    return {p.mark.mark_id: p.correction for p in preds if p.facing}
