"""Robot-mounted views with the robot's actual flange pose: re-posed cameras and predictions.

The pipeline moves the taught cameras to the actual flange pose (scene.repose) and the window
predictions of a camera place are re-posed instead of computed anew (detect.geometry); both must
give what building everything from scratch gives.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.cameras import SimScene
from mvpose_core.detect import DetectOptions, detect_marks_many
from mvpose_core.detect.geometry import (
    predict_marks,
    predict_marks_cached,
    predict_marks_cached_many,
    predict_marks_many,
)
from mvpose_core.scene import repose, sighted_marks, view_cameras
from mvpose_core.station import load_station
from mvpose_core.transforms import compose, make_transform, zyx_to_matrix

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"


@pytest.fixture(scope="module")
def lab():
    station = load_station(STATIONS / "lab.yaml")
    return station, station.recipe()


def _nudged(station, view: int, mm: float, deg: float):
    """The taught flange pose of ``view`` moved by ``mm`` and turned by ``deg`` (a robot's
    actual pose at that view)."""
    taught = station.view(view).T_rf_from_gf.matrix
    return compose(taught, make_transform(zyx_to_matrix(deg, -deg, deg), [mm, -mm, mm]))


def test_repose_equals_building_the_cameras_again(lab):
    station, _ = lab
    taught = view_cameras(station)
    actual = {1: _nudged(station, 1, 0.5, 0.05)}
    moved = repose(taught, station, actual)
    fresh = view_cameras(station, flange_poses=actual)
    for a, b, t in zip(moved, fresh, taught, strict=True):
        assert (a.view, a.camera_id) == (b.view, b.camera_id)
        np.testing.assert_allclose(a.T_rf_from_cf, b.T_rf_from_cf, atol=1e-9)
        if a.view == 2:  # no actual pose for view 2: the very same taught objects
            assert a is t
        else:
            assert a is not t and a.model is t.model
            assert np.abs(a.T_rf_from_cf[:3, 3] - t.T_rf_from_cf[:3, 3]).max() > 0.1


def test_fixed_cameras_are_not_moved():
    station = load_station(STATIONS / "station1.yaml")
    taught = view_cameras(station)
    moved = repose(taught, station, {1: np.eye(4)})
    assert all(a is b for a, b in zip(moved, taught, strict=True))


@pytest.mark.parametrize(("mm", "deg"), [(0.02, 0.002), (0.5, 0.02)])
def test_reposed_prediction_matches_a_fresh_one(lab, mm: float, deg: float):
    station, recipe = lab
    T = recipe.T_rf_from_pf0.matrix
    taught = [c for c in view_cameras(station) if c.view == 1]
    for cam in taught:
        predict_marks_cached(cam, recipe, T)  # the place's first prediction
    moved = repose(taught, station, {1: _nudged(station, 1, mm, deg)})
    for cam in moved:
        got = predict_marks_cached(cam, recipe, T)
        want = predict_marks(cam, recipe, T)
        assert [p.mark.mark_id for p in got] == [p.mark.mark_id for p in want]
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g.uv, w.uv, atol=1e-9)
            np.testing.assert_allclose(g.ellipse.centre, w.ellipse.centre, atol=1e-3)
            np.testing.assert_allclose(g.correction, w.correction, atol=1e-3)
            np.testing.assert_allclose(g.mark.n_cf, w.mark.n_cf, atol=1e-9)
            # the reach changes to second order: well within the windows' own margin
            margin = DetectOptions().window_extra_px
            assert abs(g.max_shift_px - w.max_shift_px) < min(0.25 * margin, 0.01 * w.max_shift_px)
            np.testing.assert_allclose(g.radius_range, w.radius_range, atol=0.05)
            assert g.facing == w.facing


def test_a_far_pose_is_predicted_anew(lab):
    station, recipe = lab
    T = recipe.T_rf_from_pf0.matrix
    taught = [c for c in view_cameras(station) if c.view == 1]
    for cam in taught:
        predict_marks_cached(cam, recipe, T)
    moved = repose(taught, station, {1: _nudged(station, 1, 30.0, 1.0)})  # beyond 1 % of reach
    for cam in moved:
        got = predict_marks_cached(cam, recipe, T)
        want = predict_marks(cam, recipe, T)
        for g, w in zip(got, want, strict=True):
            assert g.max_shift_px == w.max_shift_px and g.radius_range == w.radius_range
            np.testing.assert_array_equal(g.ellipse.centre, w.ellipse.centre)


def test_detection_with_reposed_cameras_equals_fresh_cameras(lab):
    station, recipe = lab
    T = recipe.T_rf_from_pf0.matrix
    actual = {1: _nudged(station, 1, 0.03, 0.003)}
    scene = SimScene(station, recipe, np.random.default_rng(3))
    scene.set_view(1, actual[1])
    scene.set_part_pose(T)
    taught = [c for c in view_cameras(station) if c.view == 1]
    opts = DetectOptions(correct_perspective=True)
    detect_marks_many([(scene.frame(c.camera_id), c) for c in taught], recipe, T, opts)
    moved = repose(taught, station, actual)
    fresh = [c for c in view_cameras(station, flange_poses=actual) if c.view == 1]
    got = detect_marks_many([(scene.frame(c.camera_id), c) for c in moved], recipe, T, opts)
    want = detect_marks_many([(scene.frame(c.camera_id), c) for c in fresh], recipe, T, opts)
    found = 0
    for gs, ws in zip(got, want, strict=True):
        for g, w in zip(gs, ws, strict=True):
            assert g.found == w.found
            if g.found:
                found += 1
                np.testing.assert_allclose(g.uv, w.uv, atol=1e-3)
    assert found == 4


def test_a_reposed_problem_equals_one_packed_from_scratch(lab):
    """The packed problem of re-posed cameras reuses the taught lenses and layout and has the
    new poses row by row: the same arrays as a problem built from freshly made cameras."""
    from mvpose_core.problem import Observation, build_problem

    station, recipe = lab
    taught = view_cameras(station)
    marks = {m.id: np.asarray(m.position, dtype=float) for m in recipe.marks}
    obs = [Observation(c.view, c.camera_id, m, np.array([1000.0 + i, 900.0 - i]))
           for i, (c, m) in enumerate((c, m) for c in taught for m in sorted(marks)[:3])]
    first = build_problem(obs, taught, marks, 0.1)
    actual = {1: _nudged(station, 1, 0.5, 0.05)}
    moved = build_problem(obs, repose(taught, station, actual), marks, 0.1)
    fresh = build_problem(obs, view_cameras(station, flange_poses=actual), marks, 0.1)
    assert moved.table.lenses is first.table.lenses  # found again by the lens objects
    for name in ("R_cf_from_rf", "t_cf_from_rf", "p_pf", "uv", "weight", "f", "c", "k"):
        np.testing.assert_allclose(getattr(moved.pk, name), getattr(fresh.pk, name), atol=1e-9,
                                   err_msg=name)
    np.testing.assert_allclose(moved.centres_rf, fresh.centres_rf, atol=1e-9)
    np.testing.assert_allclose(moved.R_rf_from_cf, fresh.R_rf_from_cf, atol=1e-12)
    view1 = [k for k, (v, _, _) in enumerate(moved.keys) if v == 1]
    assert np.abs(moved.centres_rf[view1] - first.centres_rf[view1]).max() > 0.1
    with pytest.raises(ValueError):  # shared with the next trigger's problem: read-only
        moved.pk.R_cf_from_rf[0, 0, 0] = 1.0


# The windows around a displaced part's pose are predicted in every camera at once: each
# camera's predictions are those it gets alone, to the last bit, on every example station (a
# camera with no marks of the recipe gets none); remembered as predict_marks_cached remembers.
@pytest.mark.parametrize("name", ["lab", "station1", "station2"])
def test_predictions_for_several_cameras_at_once_are_each_cameras_own(name: str) -> None:
    station = load_station(STATIONS / f"{name}.yaml")
    recipe = station.recipe()
    cams = view_cameras(station)
    T = compose(recipe.T_rf_from_pf0.matrix, make_transform(zyx_to_matrix(3.0, -2.0, 4.0),
                                                            [40.0, -30.0, 20.0]))
    ids = [(c, sighted_marks(recipe, c.view, c.camera_id)) for c in cams]
    for reach in (0.25, 1.0):
        many = predict_marks_many(ids + [(cams[0], [])], recipe, T, 0.15, 8.0, reach)
        assert many[-1] == []
        for (cam, _), got in zip(ids, many, strict=False):
            want = predict_marks(cam, recipe, T, 0.15, 8.0, reach=reach)
            assert [p.mark.mark_id for p in got] == [p.mark.mark_id for p in want]
            for a, b in zip(got, want, strict=True):
                assert (a.facing, a.dark, a.radius_range, a.ratio_range, a.max_shift_px) == (
                    b.facing, b.dark, b.radius_range, b.ratio_range, b.max_shift_px)
                for x, y in ((a.uv, b.uv), (a.correction, b.correction),
                             (a.ellipse.centre, b.ellipse.centre)):
                    assert np.array_equal(x, y)
        cached = predict_marks_cached_many(cams, recipe, T, 0.15, 8.0, reach)
        for cam, got in zip(cams, cached, strict=True):
            assert predict_marks_cached(cam, recipe, T, 0.15, 8.0, reach) is got
