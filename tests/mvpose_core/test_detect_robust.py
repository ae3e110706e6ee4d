"""Detector robustness: clutter, occlusion, bad images, and the stereo identity check."""

from __future__ import annotations

import re
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvpose_core.detect import (
    DetectOptions,
    ImageFormatError,
    MarkDetection,
    detect_marks,
    detect_marks_many,
    epipolar_distance_px,
    predict_marks,
    recorrect,
    search_marks,
    stereo_check,
)
from mvpose_core.detect.ellipse import Ellipse
from mvpose_core.detect.refine import measure_in
from mvpose_core.reasons import Reason
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.render_scene import plate_scene
from mvpose_core.scene import view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import xyzwpr_to_matrix

LAB = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "lab.yaml"


@pytest.fixture(scope="module")
def lab():  # type: ignore[no-untyped-def]
    station = load_station(LAB)
    return view_cameras(station), station.recipe()


def test_clutter_set_gives_no_false_marks_and_occluded_marks_are_missing(lab) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    rng = np.random.default_rng(11)
    found = missing_ok = 0
    for seed_round in range(3):
        for cam in cams:
            ids = [
                m
                for s in recipe.sightings
                if s.view == cam.view and s.camera == cam.camera_id
                for m in s.marks
            ]
            hidden = (ids[seed_round % len(ids)],)
            r = render_view(cam, recipe, T0, rng, RenderOptions(clutter=True, occluded=hidden))
            for d in detect_marks(r.image, cam, recipe, T0):
                if d.mark_id in hidden:
                    assert not d.found, f"occluded {d.mark_id} in {cam.key} accepted at {d.uv}"
                    assert d.reason
                    missing_ok += 1
                else:
                    assert d.found, f"{d.mark_id} in {cam.key}: {d.reason}"
                    # Found means found right: never a clutter blob instead of the mark.
                    assert np.linalg.norm(d.uv - r.centres[d.mark_id]) < 0.05
                    found += 1
    assert found == 12 and missing_ok == 12


def test_pure_clutter_without_marks_yields_nothing() -> None:
    cam, recipe = plate_scene(width=1024, height=768)
    T0 = recipe.T_rf_from_pf0.matrix
    far = T0.copy()
    far[0, 3] += 5000.0  # the part is gone; only the clutter anchored anywhere remains
    r = render_view(cam, recipe, far, np.random.default_rng(3), RenderOptions(clutter=True))
    assert not any(d.found for d in detect_marks(r.image, cam, recipe, T0))


@pytest.mark.parametrize(
    "image,match",
    [
        (np.zeros((480, 640), np.float32), "expected 640x480 mono8, got 640x480 float32"),
        (np.zeros((480, 640), np.uint16), "expected 640x480 mono8, got 640x480 mono16"),
        (np.zeros((480, 640, 3), np.uint8), "expected 640x480 mono8, got 640x480 3-channel 8-bit"),
        (np.zeros((479, 640), np.uint8), "expected 640x480 mono8, got 640x479 mono8"),
        (np.zeros((960, 1280), np.uint8), "expected 640x480 mono8, got 1280x960 mono8"),
        (np.zeros((0, 640), np.uint8), "empty"),
        ([[0, 1], [2, 3]], "expected 640x480 mono8, got list"),
    ],
)
def test_bad_images_give_a_clear_error(image, match) -> None:  # type: ignore[no-untyped-def]
    cam, recipe = plate_scene()
    with pytest.raises(ImageFormatError, match=match) as err:
        detect_marks(image, cam, recipe, recipe.T_rf_from_pf0.matrix)
    assert "camera 'v1/cam'" in str(err.value)
    assert err.value.reason == Reason.DETECTION_FAILED
    with pytest.raises(ValueError, match=match):
        search_marks(image, cam, recipe)


@pytest.mark.parametrize("fill", [0, 255, 128, "noise", "checker"])
def test_degenerate_images_report_every_mark_missing(fill) -> None:  # type: ignore[no-untyped-def]
    cam, recipe = plate_scene()
    if fill == "noise":
        image = np.random.default_rng(0).integers(0, 256, (480, 640), dtype=np.uint8)
    elif fill == "checker":
        image = ((np.indices((480, 640)).sum(axis=0) % 2) * 255).astype(np.uint8)
    else:
        image = np.full((480, 640), fill, np.uint8)
    dets = detect_marks(image, cam, recipe, recipe.T_rf_from_pf0.matrix)
    assert len(dets) == len(recipe.marks)
    assert all(not d.found and d.reason for d in dets)
    assert search_marks(image, cam, recipe) == []


def test_marks_cut_by_the_image_border_are_missing_not_biased() -> None:
    cam, recipe = plate_scene(grid=(3, 1), pitch_mm=105.0)  # outer marks at u ≈ 14, 625
    T0 = recipe.T_rf_from_pf0.matrix
    r = render_view(cam, recipe, T0, np.random.default_rng(8), RenderOptions())
    dets = {d.mark_id: d for d in detect_marks(r.image, cam, recipe, T0)}
    assert dets["M2"].found and np.linalg.norm(dets["M2"].uv - r.centres["M2"]) < 0.05
    for mid in ("M1", "M3"):  # half outside the frame: a centre from half a rim would be biased
        assert not dets[mid].found and "border" in str(dets[mid].reason)


def test_stereo_check_keeps_consistent_marks_and_drops_a_wrong_blob(lab) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    rng = np.random.default_rng(12)
    view1 = [c for c in cams if c.view == 1]
    dets = {
        c.key: detect_marks(render_view(c, recipe, T0, rng).image, c, recipe, T0) for c in view1
    }
    kept, failures = stereo_check(dets, view1)
    assert failures == [] and kept == {k: list(v) for k, v in dets.items()}
    # The left camera takes a blob 25 px below M2 for M2 (what a swap with clutter looks like).
    left = dets["v1/left"]
    bad = [replace(d, uv=d.uv + np.array([0.0, 25.0])) if d.mark_id == "M2" else d for d in left]
    kept, failures = stereo_check({**dets, "v1/left": bad}, view1)
    assert [(f.mark_id, f.camera_a, f.camera_b) for f in failures] == [
        ("M2", "v1/left", "v1/right")
    ]
    assert failures[0].distance_px > 10
    for key in ("v1/left", "v1/right"):
        status = {d.mark_id: (d.found, d.reason) for d in kept[key]}
        assert status["M3"] == (True, None)
        assert status["M2"][0] is False and "epipolar" in status["M2"][1]


def test_epipolar_distance_is_small_for_true_projections(lab) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = lab
    from mvpose_core.scene import project_recipe_marks

    left, right = cams[0], cams[1]
    pl = {p.mark_id: p.uv for p in project_recipe_marks(left, recipe, recipe.T_rf_from_pf0.matrix)}
    pr = {p.mark_id: p.uv for p in project_recipe_marks(right, recipe, recipe.T_rf_from_pf0.matrix)}
    for mid in pl:
        assert epipolar_distance_px(left, pl[mid], right, pr[mid]) < 1e-6
        assert epipolar_distance_px(left, pl[mid], right, pr[mid] + [0.0, 3.0]) > 2.0


def test_stereo_check_refuses_unknown_cameras(lab) -> None:  # type: ignore[no-untyped-def]
    cams, _ = lab
    with pytest.raises(ValueError, match="unknown cameras"):
        stereo_check({"v9/nope": [MarkDetection.missing("M1", "x")]}, cams)


def test_stereo_check_with_three_cameras_drops_only_the_odd_one_out() -> None:
    from mvpose_core.scene import ViewCamera, project_recipe_marks
    from mvpose_core.transforms import make_transform

    cam, recipe = plate_scene()
    cams = [
        ViewCamera(
            view=1,
            camera_id=name,
            model=cam.model,
            T_rf_from_cf=make_transform(np.eye(3), [x, y, 0]),
        )
        for name, x, y in (("a", 0.0, 0.0), ("b", 120.0, 0.0), ("c", 0.0, 120.0))
    ]
    T = recipe.T_rf_from_pf0.matrix
    dets = {
        c.key: [
            MarkDetection(mark_id=p.mark_id, found=True, uv=p.uv)
            for p in project_recipe_marks(c, recipe, T, only_sighted=False)
        ]
        for c in cams
    }
    dets["v1/c"] = [
        replace(d, uv=d.uv + [6.0, 0.0]) if d.mark_id == "M1" else d for d in dets["v1/c"]
    ]
    kept, failures = stereo_check(dets, cams)
    assert sorted((f.camera_a, f.camera_b) for f in failures) == [
        ("v1/a", "v1/c"),
        ("v1/b", "v1/c"),
    ]
    dropped = {(k, d.mark_id) for k, ds in kept.items() for d in ds if not d.found}
    assert dropped == {("v1/c", "M1")}


def test_several_images_detected_in_one_batch_agree_with_one_at_a_time(lab) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    rng = np.random.default_rng(31)
    T = T0 @ random_displacement(rng, 5.0, 0.5)
    frames = [(render_view(c, recipe, T, rng).image, c) for c in cams]
    with ThreadPoolExecutor(2) as pool:
        batched = detect_marks_many(frames, recipe, T0, map_fn=pool.map)
    assert len(batched) == len(frames)
    for (image, cam), dets in zip(frames, batched, strict=True):
        alone = detect_marks(image, cam, recipe, T0)
        assert [d.mark_id for d in dets] == [d.mark_id for d in alone]
        assert [d.found for d in dets] == [d.found for d in alone]
        assert any(d.found for d in dets), cam.key
        for a, b in zip(dets, alone, strict=True):
            if a.found:  # a blob's measurement depends on that blob and its image only
                assert np.abs(a.uv_ellipse - b.uv_ellipse).max() < 1e-9, (cam.key, a.mark_id)
                # a part off its prior is corrected at the pose of the centres found (settle.py):
                # those of all images, or of this one alone
                assert np.abs(a.uv - b.uv).max() < 1e-3, (cam.key, a.mark_id)


# Images whose largest marks differ in size get their own count of fine rays (80 and 96 here)
# and are measured in one pass: each candidate's result is the one it gets in its image alone.
def test_images_with_different_ray_counts_measure_as_alone() -> None:
    rng = np.random.default_rng(5)
    images, starts = [], []
    for radius, centre in ((19.3, (100.4, 97.8)), (29.6, (101.7, 103.2))):
        yy, xx = np.mgrid[0:200, 0:200].astype(float)
        d = np.hypot(xx - centre[0], (yy - centre[1]) * 1.1)  # slightly elliptical
        img = 200.0 - 140.0 * np.clip(radius - d + 0.5, 0.0, 1.0) + rng.normal(0.0, 2.0, d.shape)
        images.append(np.clip(img, 0, 255).astype(np.uint8))
        starts.append(Ellipse(np.array(centre) + [1.5, -1.0], radius + 1.0, radius - 1.0, 0.3))
    args = (20.0, 0.5, 0.8)  # min contrast, largest fit residual, edge fraction
    both = measure_in(images, np.array([0, 1]), starts, True, *args, search_px=4.0)
    for k, (image, start) in enumerate(zip(images, starts, strict=True)):
        (alone,) = measure_in([image], np.array([0]), [start], True, *args, search_px=4.0)
        assert alone.ellipse is not None and both[k].ellipse is not None
        assert both[k].edge_points == alone.edge_points
        assert np.abs(both[k].ellipse.centre - alone.ellipse.centre).max() < 1e-9
        assert abs(both[k].contrast - alone.contrast) < 1e-9
    assert both[0].edge_points <= 80 < both[1].edge_points
    # candidates out of their images' order are read by index, not as slices: the same results
    swapped = measure_in(images, np.array([1, 0]), starts[::-1], True, *args, search_px=4.0)
    for a, b in zip(swapped[::-1], both, strict=True):
        assert a.ellipse is not None and b.ellipse is not None
        assert a.edge_points == b.edge_points
        assert np.abs(a.ellipse.centre - b.ellipse.centre).max() < 1e-9


def test_a_bad_image_in_a_batch_names_its_camera(lab) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    good = render_view(cams[0], recipe, T0, np.random.default_rng(1)).image
    with pytest.raises(ValueError, match=re.escape(f"camera {cams[1].key!r}")):
        detect_marks_many([(good, cams[0]), (good[:100], cams[1])], recipe, T0)


# Near the taught pose the small windows find every mark, from blobs found at their own (maybe
# coarser) reduction: the measurement starts elsewhere and ends within the detector's noise
# (~0.01 px at image noise 2; the accuracy tests in test_detect.py run with the first reach).
# Beyond the first reach (a quarter of the lab's
# ±100 mm / ±10°) the image is searched again over the whole tolerance: the one-pass result.
@pytest.mark.parametrize("mm,deg,agree_px", [(5.0, 0.5, 0.01), (60.0, 6.0, 1e-9)])
def test_the_first_reach_finds_what_the_whole_tolerance_finds(  # type: ignore[no-untyped-def]
    lab, mm: float, deg: float, agree_px: float
) -> None:
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    assert mm > 0.25 * recipe.tolerances.max_offset_mm or mm < 0.1 * recipe.tolerances.max_offset_mm
    T = T0 @ xyzwpr_to_matrix([mm, -mm, 0.5 * mm, deg, -deg, 0.5 * deg])
    rng = np.random.default_rng(41)
    frames = [(render_view(c, recipe, T, rng).image, c) for c in cams]
    assert DetectOptions().first_reach(recipe.tolerances.max_offset_mm,
                                       recipe.tolerances.max_offset_deg) == pytest.approx(0.25)
    two = detect_marks_many(frames, recipe, T0, DetectOptions())
    one = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    assert sum(d.found for dets in one for d in dets) == sum(len(dets) for dets in one)
    for a_dets, b_dets in zip(two, one, strict=True):
        for a, b in zip(a_dets, b_dets, strict=True):
            assert a.found and a.mark_id == b.mark_id
            assert np.abs(a.uv - b.uv).max() < agree_px


def test_windows_of_the_first_reach_are_smaller(lab) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    for cam in cams:
        near = predict_marks(cam, recipe, T0, reach=0.25)
        full = predict_marks(cam, recipe, T0)
        for a, b in zip(near, full, strict=True):
            assert a.max_shift_px < 0.5 * b.max_shift_px
            assert b.radius_range[0] <= a.radius_range[0] < a.radius_range[1] <= b.radius_range[1]
            assert np.array_equal(a.correction, b.correction)


def test_the_first_reach_is_used_only_inside_wider_tolerances() -> None:
    opts = DetectOptions(first_reach_mm=25.0, first_reach_deg=2.5)
    assert opts.first_reach(100.0, 10.0) == pytest.approx(0.25)
    assert opts.first_reach(50.0, 10.0) == pytest.approx(0.5)  # the larger share of the two
    assert opts.first_reach(20.0, 2.0) is None  # no wider than the first reach: one search
    assert DetectOptions(first_reach_mm=None).first_reach(100.0, 10.0) is None
    for mm, deg in ((0.0, 2.5), (-1.0, 2.5), (25.0, 0.0)):
        with pytest.raises(ValueError, match="first_reach"):
            DetectOptions(first_reach_mm=mm, first_reach_deg=deg)


# A displaced part: images whose small windows hold no blob for some mark go straight to the
# whole tolerance's windows and are measured once. Every mark is found, at the centre the
# one-pass search (first_reach_mm=None) measures, from beyond the first reach to the tolerance:
# exactly for an image searched again, within the detector's noise (~0.01 px) for one whose
# marks all lay in their small windows (the measurement starts from another blob there); an
# image searched around the blobs' pose carries the correction at that pose, so the centres are
# compared before the correction and with both corrected at the part's pose.
@pytest.mark.parametrize("share", [0.5, 0.75, 1.0])
def test_a_displaced_part_is_found_where_the_whole_tolerance_finds_it(  # type: ignore[no-untyped-def]
    lab, share: float
) -> None:
    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    tol = recipe.tolerances
    mm, deg = share * tol.max_offset_mm / 1.8, share * tol.max_offset_deg / 1.8
    T = T0 @ xyzwpr_to_matrix([mm, -mm, 0.5 * mm, deg, -deg, 0.5 * deg])
    rng = np.random.default_rng(43)
    frames = [(render_view(c, recipe, T, rng).image, c) for c in cams]
    two = detect_marks_many(frames, recipe, T0, DetectOptions())
    one = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    for a_dets, b_dets in zip(two, one, strict=True):
        for a, b in zip(a_dets, b_dets, strict=True):
            assert a.found and b.found and a.mark_id == b.mark_id
            assert np.abs(a.uv_ellipse - b.uv_ellipse).max() < 0.01
    two_at, _ = recorrect(list(zip(cams, two, strict=True)), recipe, T)
    one_at, _ = recorrect(list(zip(cams, one, strict=True)), recipe, T)
    for a_dets, b_dets in zip(two_at, one_at, strict=True):
        for a, b in zip(a_dets, b_dets, strict=True):
            assert np.abs(a.uv - b.uv).max() < 0.01


def test_an_image_with_a_blobless_window_is_sent_to_the_whole_tolerance(lab) -> None:  # type: ignore[no-untyped-def]
    from mvpose_core.detect.layout import search_windows
    from mvpose_core.detect.window import _unfound

    cams, recipe = lab
    T0 = recipe.T_rf_from_pf0.matrix
    near = render_view(cams[0], recipe, T0, np.random.default_rng(5)).image
    far = render_view(cams[0], recipe, T0 @ xyzwpr_to_matrix([50.0, -50.0, 25.0, 5.0, -5.0, 2.5]),
                      np.random.default_rng(5)).image
    opts = DetectOptions()
    assert not _unfound(search_windows(near, cams[0], recipe, T0, opts, 0.25), opts)
    assert _unfound(search_windows(far, cams[0], recipe, T0, opts, 0.25), opts)
    assert not _unfound(search_windows(far, cams[0], recipe, T0, opts, 1.0), opts)
