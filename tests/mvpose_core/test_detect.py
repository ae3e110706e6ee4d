"""Detector accuracy and window mode on rendered images with known truth (issue 4 acceptance)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from mvpose_core.detect import (
    DetectOptions,
    correct_centres,
    detect_marks,
    identify_marks,
    perspective_correction,
    recorrect,
    search_marks,
)
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.render_scene import plate_scene
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import compose, xyzwpr_to_matrix

NOISE2 = RenderOptions(noise_sigma=2.0, shot_noise_gain=0.0)


def _errors(cam, recipe, n_images: int, seed: int, opts: RenderOptions):  # type: ignore[no-untyped-def]
    """Corrected and uncorrected centre errors over images of slightly moved parts."""
    rng = np.random.default_rng(seed)
    T0 = recipe.T_rf_from_pf0.matrix
    err, raw = [], []
    for _ in range(n_images):
        T = T0 @ random_displacement(rng, 1.0, 0.2)  # new sub-pixel phases every image
        r = render_view(cam, recipe, T, rng, opts)
        for d in detect_marks(r.image, cam, recipe, T0):
            assert d.found, (d.mark_id, d.reason)
            err.append(d.uv - r.centres[d.mark_id])
            raw.append(d.uv_ellipse - r.centres[d.mark_id])
    return np.array(err), np.array(raw)


def test_centre_std_at_noise_2_for_radius_6px() -> None:
    cam, recipe = plate_scene(mark_diameter_mm=4.2, grid=(4, 3))  # radius ≈ 6.1 px
    err, _ = _errors(cam, recipe, 8, seed=1, opts=NOISE2)
    assert len(err) == 96
    std = err.std(axis=0)
    assert np.all(std <= 0.02), std
    assert np.all(np.abs(err.mean(axis=0)) <= 0.01)


@pytest.mark.parametrize("tilt_deg,diameter_mm", [(30.0, 12.0), (40.0, 16.0)])
def test_bias_after_perspective_correction_on_tilted_marks(
    tilt_deg: float, diameter_mm: float
) -> None:
    cam, recipe = plate_scene(tilt_deg=tilt_deg, mark_diameter_mm=diameter_mm)
    err, raw = _errors(cam, recipe, 6, seed=2, opts=NOISE2)
    # Without the correction the ellipse centre is off by several hundredths of a pixel ...
    assert np.linalg.norm(raw.mean(axis=0)) > 0.03
    # ... with it, the bias is within 0.01 px per axis.
    assert np.all(np.abs(err.mean(axis=0)) <= 0.01), err.mean(axis=0)
    assert np.all(err.std(axis=0) <= 0.02)


def test_correct_centres_recomputes_the_correction_at_a_new_pose() -> None:
    cam, recipe = plate_scene(tilt_deg=35.0, mark_diameter_mm=16.0)
    T0 = recipe.T_rf_from_pf0.matrix
    r = render_view(cam, recipe, T0, np.random.default_rng(3), NOISE2)
    dets = detect_marks(r.image, cam, recipe, T0)
    T1 = compose(T0, xyzwpr_to_matrix([0, 0, 0, 0, 12.0, 0]))  # a different tilt
    moved = correct_centres(dets, cam, recipe, T1)
    corr = perspective_correction(cam, recipe, T1, [d.mark_id for d in dets])
    for d, m in zip(dets, moved, strict=True):
        assert not np.allclose(d.correction, corr[d.mark_id], atol=1e-3)
        np.testing.assert_allclose(m.uv, d.uv_ellipse + corr[d.mark_id], atol=1e-12)
        np.testing.assert_allclose(m.uv_ellipse, d.uv_ellipse)


def test_recorrect_reports_how_far_the_correction_moved_over_all_cameras() -> None:
    cam, recipe = plate_scene(tilt_deg=35.0, mark_diameter_mm=16.0)
    T0 = recipe.T_rf_from_pf0.matrix
    r = render_view(cam, recipe, T0, np.random.default_rng(3), NOISE2)
    dets = detect_marks(r.image, cam, recipe, T0)
    dets[1] = replace(dets[1], found=False, uv=None)  # a missed mark is passed through
    same, shift0 = recorrect([(cam, dets), (cam, dets)], recipe, T0)
    assert shift0 < 1e-9  # at the prior pose: the correction detection already applied
    T1 = compose(T0, xyzwpr_to_matrix([0, 0, 0, 0, 12.0, 0]))
    (moved, again), shift = recorrect([(cam, dets), (cam, dets)], recipe, T1)
    corr = perspective_correction(cam, recipe, T1, [d.mark_id for d in dets if d.found])
    expected = max(np.linalg.norm(corr[d.mark_id] - d.correction) for d in dets if d.found)
    assert shift == pytest.approx(expected, abs=1e-12) and shift > 1e-3
    assert moved[1] is dets[1] and again[1] is dets[1]
    for d, m in zip(dets, moved, strict=True):
        if d.found:
            np.testing.assert_allclose(m.uv, d.uv_ellipse + corr[d.mark_id], atol=1e-12)
    for d, m in zip(dets, same[0], strict=True):
        if d.found:
            np.testing.assert_allclose(m.uv, d.uv, atol=1e-9)


def test_window_mode_follows_a_displaced_part_and_keeps_identities() -> None:
    cam, recipe = plate_scene(width=1024, height=768, max_offset_mm=20.0, max_offset_deg=3.0)
    T0 = recipe.T_rf_from_pf0.matrix
    rng = np.random.default_rng(4)
    for _ in range(3):
        T = T0 @ random_displacement(rng, 15.0, 2.0)
        r = render_view(cam, recipe, T, rng, RenderOptions())
        dets = detect_marks(r.image, cam, recipe, T0)
        assert [d.mark_id for d in dets] == [m.id for m in recipe.marks]
        for d in dets:
            assert d.found, d.reason
            assert np.linalg.norm(d.uv_ellipse - r.centres[d.mark_id]) < 0.1
            assert d.contrast > 100 and d.fit_residual_px < 0.1 and 0.9 < d.axis_ratio <= 1.0


def test_a_part_beyond_the_tolerance_is_missed_not_misnamed() -> None:
    cam, recipe = plate_scene(width=1024, height=768, max_offset_mm=5.0, max_offset_deg=0.5)
    T0 = recipe.T_rf_from_pf0.matrix
    T = compose(T0, xyzwpr_to_matrix([20.0, 0, 0, 0, 0, 0]))  # 58 px: next to the window, not in it
    r = render_view(cam, recipe, T, np.random.default_rng(5), RenderOptions())
    dets = detect_marks(r.image, cam, recipe, T0)
    assert not any(d.found for d in dets)
    assert all(d.reason for d in dets)


def test_light_marks_on_dark_surface() -> None:
    cam, recipe = plate_scene(polarity="light_on_dark", mark_diameter_mm=8.0)
    r = render_view(cam, recipe, recipe.T_rf_from_pf0.matrix, np.random.default_rng(6), NOISE2)
    dets = detect_marks(r.image, cam, recipe, recipe.T_rf_from_pf0.matrix)
    for d in dets:
        assert d.found and np.linalg.norm(d.uv - r.centres[d.mark_id]) < 0.05


def test_search_mode_finds_and_identify_names_marks_without_prior() -> None:
    cam, recipe = plate_scene(width=1024, height=768, max_offset_mm=20.0, max_offset_deg=3.0)
    T0 = recipe.T_rf_from_pf0.matrix
    T = compose(T0, xyzwpr_to_matrix([12.0, -8.0, 5.0, 1.0, -1.0, 2.0]))
    r = render_view(cam, recipe, T, np.random.default_rng(7), RenderOptions())
    blobs = search_marks(r.image, cam, recipe)
    assert len(blobs) == len(recipe.marks)
    assert all(b.mark_id.startswith("?") for b in blobs)
    named = identify_marks(blobs, cam, recipe, T, max_distance_px=10.0)
    for d in named:
        assert d.found and np.linalg.norm(d.uv - r.centres[d.mark_id]) < 0.05
    # With no blob near its prediction, a mark is reported missing rather than given a stranger.
    assert not any(d.found for d in identify_marks(blobs[:0], cam, recipe, T, 10.0))


def test_options_are_validated() -> None:
    with pytest.raises(ValueError, match="search_scale"):
        DetectOptions(search_scale=3)
    with pytest.raises(ValueError, match="min_contrast"):
        DetectOptions(min_contrast=-1.0)
