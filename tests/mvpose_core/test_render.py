"""Renderer: true perspective marks, anti-aliased coverage, polarity, clutter placement, options."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_core.detect.ellipse import fit_ellipse, rim_points
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.render_scene import plate_scene
from mvpose_core.scene import project_recipe_marks

CLEAN = RenderOptions(noise_sigma=0.0, blur_sigma_px=0.0, gradient=0.0, shot_noise_gain=0.0)


def _dark_mass(image: np.ndarray, uv: np.ndarray, half: int, bg: float) -> tuple[float, np.ndarray]:
    """Darkness-weighted area and centroid of the patch around ``uv``."""
    u, v = np.round(uv).astype(int)
    patch = bg - image[v - half : v + half + 1, u - half : u + half + 1].astype(float)
    vv, uu = np.mgrid[v - half : v + half + 1, u - half : u + half + 1]
    w = patch.sum()
    return w, np.array([(uu * patch).sum() / w, (vv * patch).sum() / w])


def test_centres_are_projected_circle_centres_and_image_is_mono8() -> None:
    cam, recipe = plate_scene()
    T = recipe.T_rf_from_pf0.matrix
    r = render_view(cam, recipe, T, np.random.default_rng(0))
    assert r.image.dtype == np.uint8 and r.image.shape == (480, 640)
    expected = {pm.mark_id: pm.uv for pm in project_recipe_marks(cam, recipe, T)}
    assert set(r.centres) == set(expected)
    for mid, uv in expected.items():
        np.testing.assert_allclose(r.centres[mid], uv, atol=1e-9)


def test_tilted_mark_is_the_perspective_ellipse_not_a_shifted_circle() -> None:
    """The drawn disc's area and centroid are those of the imaged ellipse, whose centre is not
    the projected circle centre (the offset the detector must correct)."""
    cam, recipe = plate_scene(tilt_deg=40.0, mark_diameter_mm=16.0)
    T = recipe.T_rf_from_pf0.matrix
    opts = RenderOptions(noise_sigma=0.0, blur_sigma_px=0.0, gradient=0.0, shot_noise_gain=0.0)
    r = render_view(cam, recipe, T, np.random.default_rng(0), opts)
    level = opts.level * (opts.light_albedo - opts.dark_albedo)
    for pm in project_recipe_marks(cam, recipe, T):
        ell = fit_ellipse(cam.model.project(rim_points(pm, 8.0, n=360)))
        assert ell is not None
        mass, centroid = _dark_mass(r.image, pm.uv, 30, opts.level * opts.light_albedo)
        assert mass / level == pytest.approx(np.pi * ell.a * ell.b, rel=0.01)
        assert np.linalg.norm(centroid - ell.centre) < 0.01
        assert np.linalg.norm(ell.centre - pm.uv) > 0.05  # the tilt really moves the centre


def test_edges_are_anti_aliased() -> None:
    cam, recipe = plate_scene(mark_diameter_mm=16.0)
    r = render_view(cam, recipe, recipe.T_rf_from_pf0.matrix, np.random.default_rng(0), CLEAN)
    lo, hi = round(235 * 0.18), round(235 * 0.78)
    values = np.unique(r.image)
    between = values[(values > lo + 1) & (values < hi - 1)]
    assert len(between) > 20  # partial coverage gives intermediate grey levels


def test_polarity_follows_the_recipe() -> None:
    for polarity, sign in (("dark_on_light", -1), ("light_on_dark", 1)):
        cam, recipe = plate_scene(polarity=polarity)
        r = render_view(cam, recipe, recipe.T_rf_from_pf0.matrix, np.random.default_rng(1), CLEAN)
        for uv in r.centres.values():
            u, v = np.round(uv).astype(int)
            centre, around = float(r.image[v, u]), float(r.image[v, u + 40])
            assert sign * (centre - around) > 100


def test_same_seed_same_image_and_noise_level() -> None:
    cam, recipe = plate_scene()
    T = recipe.T_rf_from_pf0.matrix
    opts = RenderOptions(noise_sigma=3.0, shot_noise_gain=0.0, gradient=0.0)
    a = render_view(cam, recipe, T, np.random.default_rng(5), opts).image
    b = render_view(cam, recipe, T, np.random.default_rng(5), opts).image
    c = render_view(cam, recipe, T, np.random.default_rng(6), opts).image
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    flat = (a.astype(float) - c.astype(float))[:100, :100]  # no marks there
    assert np.std(flat) / np.sqrt(2) == pytest.approx(3.0, rel=0.1)


def test_clutter_and_occluders_leave_unoccluded_marks_intact() -> None:
    cam, recipe = plate_scene(width=1024, height=768, mark_diameter_mm=14.0)
    T = recipe.T_rf_from_pf0.matrix
    opts = RenderOptions(noise_sigma=0.0, blur_sigma_px=0.0, gradient=0.0, shot_noise_gain=0.0)
    clean = render_view(cam, recipe, T, np.random.default_rng(2), opts)
    busy = render_view(
        cam,
        recipe,
        T,
        np.random.default_rng(2),
        RenderOptions(
            noise_sigma=0.0,
            blur_sigma_px=0.0,
            gradient=0.0,
            shot_noise_gain=0.0,
            clutter=True,
            occluded=("M1",),
        ),
    )
    assert busy.occluded == ("M1",)
    assert np.count_nonzero(busy.image != clean.image) > 2000  # clutter was drawn
    for mid, uv in clean.centres.items():
        u, v = np.round(uv).astype(int)
        a = clean.image[v - 3 : v + 4, u - 3 : u + 4].astype(float)
        b = busy.image[v - 3 : v + 4, u - 3 : u + 4].astype(float)
        if mid == "M1":
            continue
        # A panel edge may darken the whole panel a mark sits on, but nothing is drawn over it.
        ratio = b.mean() / a.mean()
        assert np.allclose(b, a * ratio, atol=1.5)


def test_marks_facing_away_or_outside_are_not_drawn() -> None:
    cam, recipe = plate_scene()
    T = recipe.T_rf_from_pf0.matrix.copy()
    T[0, 3] += 5000.0  # far to the side: outside the image
    r = render_view(cam, recipe, T, np.random.default_rng(0), CLEAN)
    assert r.centres == {}
    assert r.image.min() == r.image.max()


@pytest.mark.parametrize(
    "field,value", [("noise_sigma", -1.0), ("blur_sigma_px", float("nan")), ("supersample", 0)]
)
def test_bad_options_are_refused(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        RenderOptions(**{field: value})
