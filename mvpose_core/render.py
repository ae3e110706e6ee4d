"""Render realistic camera images of a station's marks with known truth, for tests, twins and demos.

Each mark is drawn as the exact perspective image of a circle of its own diameter (the mark's
``diameter_mm``, else the recipe's ``mark_diameter_mm``) and polarity lying on the part surface
(so a tilted mark is an ellipse whose centre is *not* the image of the circle's centre), through
the camera's lens distortion. Only the neighbourhood of each mark is computed
finely: pixels near the rim are super-sampled (16 × 16) by casting their sub-pixel rays onto the
mark's plane; the rest of the frame is a smooth illumination field filled with array arithmetic.
Then defocus blur, shot and read noise, and saturation to 8 bits.

The photometric model is ``grey = level · illumination(u, v) · albedo(u, v)`` with a linear
illumination gradient; clutter (panel edges, holes that are not marks, specular spots) and partial
occlusions are painted into the albedo before blurring.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from mvpose_core.camera import CameraModel
from mvpose_core.detect.ellipse import rim_points
from mvpose_core.render_clutter import paint_clutter, paint_decoy, paint_occluder
from mvpose_core.scene import ProjectedMark, ViewCamera, project_recipe_marks
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array


@dataclass(frozen=True)
class RenderOptions:
    """How an image looks; the defaults give a realistic, clean production image."""

    noise_sigma: float = 2.0  # read noise, grey levels; plus shot noise
    blur_sigma_px: float = 0.8  # defocus
    gradient: float = 0.25  # illumination gradient strength (relative change across the frame)
    clutter: bool = False  # edges, holes that are not marks, specular spots
    occluded: tuple[str, ...] = ()  # mark ids partially occluded
    occluded_fraction: tuple[float, float] = (0.4, 0.6)  # share of an occluded mark hidden
    decoys: tuple[str, ...] = ()  # mark ids with a dot of their own size painted next to them
    shot_noise_gain: float = 0.01  # shot-noise variance per grey level of signal (gl² / gl)
    level: float = 235.0  # grey level of a white surface under the mean illumination
    light_albedo: float = 0.78  # surface (dark_on_light) or mark (light_on_dark)
    dark_albedo: float = 0.18  # mark (dark_on_light) or surface (light_on_dark)
    supersample: int = 16  # sub-samples per axis on rim pixels

    def __post_init__(self) -> None:
        for name in ("noise_sigma", "blur_sigma_px", "gradient", "shot_noise_gain"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"RenderOptions.{name} must be finite and >= 0, got {v}")
        if not 1 <= self.supersample <= 64:
            raise ValueError(f"RenderOptions.supersample must be in 1..64, got {self.supersample}")


@dataclass(frozen=True)
class RenderedImage:
    """A rendered frame and its truth."""

    image: np.ndarray  # uint8 [H, W]
    # True projected CIRCLE centre (uv, [2]) of each mark drawn in the image.
    centres: dict[str, np.ndarray]
    occluded: tuple[str, ...] = ()  # marks drawn partially hidden (a detector must miss them)


def render_view(
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf: np.ndarray,
    rng: np.random.Generator,
    options: RenderOptions = RenderOptions(),  # noqa: B008 - frozen, immutable default
) -> RenderedImage:
    """Render what ``cam`` sees of the recipe's sighted marks with the part at ``T_rf_from_pf``."""
    model = cam.model
    H, W = model.height, model.width
    radii = dict(zip((m.id for m in recipe.marks), recipe.mark_diameters() / 2.0, strict=True))
    darks = dict(zip((m.id for m in recipe.marks), recipe.mark_dark().tolist(), strict=True))
    dark_marks = recipe.polarity == "dark_on_light"
    bg_albedo = options.light_albedo if dark_marks else options.dark_albedo
    mark_albedo = options.dark_albedo if dark_marks else options.light_albedo

    albedo = np.full((H, W), bg_albedo, dtype=np.float32)
    marks = [
        pm
        for pm in project_recipe_marks(cam, recipe, T_rf_from_pf)
        if pm.depth_mm > 1.0 and float(pm.n_cf @ pm.p_cf) < 0.0  # in front, facing the camera
    ]
    centres: dict[str, np.ndarray] = {}
    footprints: dict[str, tuple[Array, float]] = {}  # (uv, radius px) of drawn marks
    for pm in marks:
        radius_mm = float(radii[pm.mark_id])
        own, under = mark_albedo, bg_albedo
        if darks[pm.mark_id] != dark_marks:
            # A mark of the other polarity sits on a label of twice its diameter that contrasts
            # with it (a white dot on a black sticker, on a light panel).
            own, under = bg_albedo, mark_albedo
            _draw_mark(albedo, model, pm, 2.0 * radius_mm, under, bg_albedo, options.supersample)
        r_px = _draw_mark(albedo, model, pm, radius_mm, own, under, options.supersample)
        if r_px is None:
            continue
        centres[pm.mark_id] = pm.uv.copy()
        footprints[pm.mark_id] = (pm.uv, r_px)

    occluded = tuple(m for m in options.occluded if m in centres)
    for mid in occluded:
        uv, r = footprints[mid]
        paint_occluder(albedo, uv, r, bg_albedo, rng, options.occluded_fraction)
    for mid in options.decoys:
        if mid in footprints:
            uv, r = footprints[mid]
            paint_decoy(albedo, uv, r, mark_albedo if darks[mid] == dark_marks else bg_albedo, rng)
    if options.clutter:
        paint_clutter(albedo, list(footprints.values()), bg_albedo, mark_albedo, rng)

    if options.blur_sigma_px > 0:
        albedo = cv2.GaussianBlur(  # type: ignore[assignment]
            albedo, (0, 0), options.blur_sigma_px, borderType=cv2.BORDER_REPLICATE
        )
    signal = albedo * _illumination(H, W, options, rng)
    noisy = _add_noise(signal, options, rng)
    image = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return RenderedImage(image=image, centres=centres, occluded=occluded)


# ----------------------------------------------------------------------------- marks


def _plane_radius(model: CameraModel, uv: Array, pm: ProjectedMark) -> Array:
    """Distance (mm) from the mark centre to where each pixel's ray meets the mark's plane."""
    xy = model.undistort_normalized(uv)
    rays = np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)
    s = float(pm.n_cf @ pm.p_cf) / (rays @ pm.n_cf)
    return np.linalg.norm(rays * s[:, None] - pm.p_cf, axis=1)


def _draw_mark(
    albedo: np.ndarray,
    model: CameraModel,
    pm: ProjectedMark,
    radius_mm: float,
    mark_albedo: float,
    bg_albedo: float,
    ss: int,
) -> float | None:
    """Paint one mark's anti-aliased coverage into ``albedo``; its radius in px, None if unseen."""
    H, W = albedo.shape
    rim_uv = model.project(rim_points(pm, radius_mm))
    u0, v0 = np.floor(rim_uv.min(axis=0)).astype(int) - 2
    u1, v1 = np.ceil(rim_uv.max(axis=0)).astype(int) + 3
    if u1 <= 0 or v1 <= 0 or u0 >= W or v0 >= H:
        return None
    if not model.in_image(pm.uv[None])[0]:
        return None
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, W), min(v1, H)
    vv, uu = np.mgrid[v0:v1, u0:u1]
    centres_uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    rho = _plane_radius(model, centres_uv, pm).reshape(uu.shape)
    cover = (rho < radius_mm).astype(np.float64)
    # A pixel whose centre lies within ~1 px of the rim may be partly covered: super-sample it.
    gy, gx = np.gradient(rho)
    px_dist = np.abs(rho - radius_mm) / np.maximum(np.hypot(gx, gy), 1e-12)
    edge = px_dist < 1.0
    if edge.any():
        offs = (np.arange(ss) + 0.5) / ss - 0.5
        ou, ov = np.meshgrid(offs, offs)
        sub = centres_uv[edge.ravel()][:, None, :] + np.stack([ou.ravel(), ov.ravel()], 1)[None]
        inside = _plane_radius(model, sub.reshape(-1, 2), pm).reshape(-1, ss * ss) < radius_mm
        cover[edge] = inside.mean(axis=1)
    patch = albedo[v0:v1, u0:u1]
    patch[:] = patch + (mark_albedo - bg_albedo) * cover.astype(np.float32)
    return float(np.max(np.linalg.norm(rim_uv - pm.uv, axis=1)))


# ----------------------------------------------------------------------------- photometry


def _illumination(H: int, W: int, options: RenderOptions, rng: np.random.Generator) -> np.ndarray:
    """``level`` times a linear gradient in a random direction, mean 1 over the frame."""
    ang = rng.uniform(0.0, 2.0 * np.pi)
    gu = np.float32(options.gradient * np.cos(ang) / W)
    gv = np.float32(options.gradient * np.sin(ang) / H)
    u = (np.arange(W, dtype=np.float32) - np.float32(W / 2)) * gu
    v = (np.arange(H, dtype=np.float32) - np.float32(H / 2)) * gv
    return np.float32(options.level) * (1.0 + v[:, None] + u[None, :])


def _add_noise(signal: np.ndarray, options: RenderOptions, rng: np.random.Generator) -> np.ndarray:
    if options.noise_sigma == 0 and options.shot_noise_gain == 0:
        return signal
    noise = rng.standard_normal(signal.shape, dtype=np.float32)
    if options.shot_noise_gain == 0:
        return signal + np.float32(options.noise_sigma) * noise
    var = np.float32(options.noise_sigma**2) + np.float32(options.shot_noise_gain) * np.maximum(
        signal, 0
    )
    return signal + np.sqrt(var) * noise
