"""Simulation scenes, study definitions and the Monte Carlo runner's determinism."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_core.estimate import EstimateOptions, Observation, estimate_pose, pack_layout
from mvpose_core.refine import project
from mvpose_core.simulation.montecarlo import run_points, run_trial, summarise
from mvpose_core.simulation.scenes import (
    CAD_MARKS_4,
    PART_SIZE_MM,
    STANDOFF_MM,
    build_trial,
    random_layout,
    split_marks,
    view_poses_pf,
)
from mvpose_core.simulation.studies import (
    HANDEYE_LEVELS,
    STUDIES,
    Scenario,
    StudyPoint,
    get_study,
)
from mvpose_core.transforms import compose, invert, matrix_to_rotvec, transform_error


def test_random_layout_spacing_and_extent() -> None:
    rng = np.random.default_rng(3)
    for n in (4, 18, 20):
        p = random_layout(n, rng)
        assert p.shape == (n, 3)
        assert np.all(np.abs(p[:, 0]) <= PART_SIZE_MM[0] / 2) and np.all(
            np.abs(p[:, 1]) <= PART_SIZE_MM[1] / 2
        )
        d = np.linalg.norm(p[:, None, :2] - p[None, :, :2], axis=2) + np.eye(n) * 1e9
        assert d.min() >= 80.0
    with pytest.raises(ValueError, match="cannot place 500 marks"):
        random_layout(500, rng)


@pytest.mark.parametrize("n_views", [1, 2, 6, 18, 20])
def test_split_marks_sees_every_mark(n_views: int) -> None:
    p = random_layout(18, np.random.default_rng(1))
    groups = split_marks(p, n_views)
    assert len(groups) == n_views and all(groups)
    seen = [m for g in groups for m in g]
    assert sorted(set(seen)) == list(range(18))
    assert len(seen) == max(18, n_views)  # each mark once until there are more views than marks


@pytest.mark.parametrize("motion", ["rotate", "translate"])
def test_views_are_rotations_looking_at_their_targets(motion: str) -> None:
    targets = np.array([[100.0, -50.0, 10.0], [-400.0, 200.0, -20.0], [0.0, 0.0, 0.0]])
    T = view_poses_pf(targets, motion, np.random.default_rng(4))  # type: ignore[arg-type]
    for Ti, target in zip(T, targets, strict=True):
        R = Ti[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        p_rig = invert(Ti) @ np.append(target, 1.0)
        np.testing.assert_allclose(p_rig[:2], 0.0, atol=1e-9)  # on the optical axis
        assert p_rig[2] == pytest.approx(STANDOFF_MM)
        assert Ti[2, 3] > target[2]  # above the part, looking down at it


def test_noiseless_trial_is_recovered_exactly_and_marks_are_in_front() -> None:
    rng = np.random.default_rng(5)
    trial = build_trial(random_layout(18, rng), 6, rng)
    T = trial.T_rf_from_pf
    pk, _ = pack_layout(trial.cameras_true, trial.marks_pf, trial.layout)
    uv, p_cf = project(pk, T[:3, :3], T[:3, 3])
    assert np.all(p_cf[:, 2] > 0.5 * STANDOFF_MM)
    obs = [Observation(v, c, m, uv[i]) for i, (v, c, m) in enumerate(trial.layout)]
    for objective in ("all", "left_only"):
        r = estimate_pose(
            obs, trial.cameras_believed, trial.marks_pf, EstimateOptions(objective=objective)
        )
        deg, mm = transform_error(r.T_rf_from_pf, T)
        assert deg < 1e-6 and mm < 1e-5


def test_translate_motion_keeps_one_rig_orientation() -> None:
    rng = np.random.default_rng(2)
    for motion, same in (("translate", True), ("rotate", False)):
        trial = build_trial(CAD_MARKS_4, 2, rng, motion)  # type: ignore[arg-type]
        left = [c.T_rf_from_cf for c in trial.cameras_true if c.camera_id == "left"]
        angle = np.degrees(np.linalg.norm(matrix_to_rotvec(left[0][:3, :3].T @ left[1][:3, :3])))
        assert bool(angle < 1e-9) is same, (motion, angle)


def test_hand_eye_error_spares_the_first_view_and_has_the_stated_size() -> None:
    rng = np.random.default_rng(9)
    lv = HANDEYE_LEVELS["high"]
    rot, trans = [], []
    for _ in range(300):
        trial = build_trial(CAD_MARKS_4, 3, rng, "rotate", lv.rot_deg, lv.trans_mm)
        for t, b in zip(trial.cameras_true, trial.cameras_believed, strict=True):
            err = compose(invert(t.T_rf_from_cf), b.T_rf_from_cf)
            if t.view == 1:
                np.testing.assert_allclose(err, np.eye(4), atol=1e-9)
            elif t.camera_id == "left":
                rot.append(np.degrees(matrix_to_rotvec(err[:3, :3])))
    rot = np.array(rot)
    # per-axis 1σ of the rig error (the camera frame is rotated, the angle's size is not)
    assert np.sqrt(np.mean(np.sum(rot**2, axis=1)) / 3) == pytest.approx(lv.rot_deg, rel=0.1)
    del trans


def test_studies_follow_the_paper_settings() -> None:
    noise = get_study("noise")
    assert {(p.scenario.n_marks, p.scenario.n_views) for p in noise.points} == {(4, 2)}
    marks = get_study("marks")
    assert [p.scenario.n_marks for p in marks.points][0] == 4 and marks.points[
        -1
    ].scenario.n_marks == 20
    assert all(p.scenario.sigma_px == 1.0 and p.scenario.n_views == 2 for p in marks.points)
    views = get_study("views")
    assert {p.scenario.n_marks for p in views.points} == {18}
    assert {p.x for p in views.points} >= {1, 6, 20}
    assert {p.scenario.handeye.name for p in views.points} == {"zero", "low", "high"}
    motions = {p.scenario.motion for p in get_study("translation-only").points}
    assert motions == {"translate", "rotate"}
    keys = [p.seed_key for s in STUDIES.values() for p in s.points]
    assert len(keys) == len(set(keys))  # every point has its own random stream
    with pytest.raises(ValueError, match="unknown study 'bogus'"):
        get_study("bogus")
    with pytest.raises(ValueError, match="sigma_px must be ≥ 0"):
        Scenario(4, 2, -1.0)


def test_run_points_is_deterministic_whatever_the_worker_count() -> None:
    pts = [get_study("noise").points[3], get_study("views").points[-1]]
    one = run_points(pts, 30, 7, workers=1)
    two = run_points(pts, 30, 7, workers=2)
    for a, b in zip(one, two, strict=True):
        assert a.shape == (30, 2, 4)
        np.testing.assert_array_equal(a, b)
    other = run_points(pts[:1], 30, 8, workers=1)
    assert not np.array_equal(other[0], one[0])
    # a point's numbers do not depend on which other points run beside it
    np.testing.assert_array_equal(run_points(pts[:1], 30, 7, workers=1)[0], one[0])


def test_zero_noise_trial_has_zero_error_and_zero_bound() -> None:
    sc = Scenario(4, 2, 0.0, layout="cad")
    out = run_trial(sc, np.random.default_rng(0))
    assert np.all(out[:, :2] < 1e-5) and np.all(out[:, 2:] == 0.0)


def test_summary_counts_failures_and_reports_nan_free_statistics() -> None:
    p = StudyPoint("t", "s", 1.0, Scenario(4, 2, 1.0, layout="cad"), (99,))
    samples = run_points([p], 20, 1, workers=1)[0]
    samples[3, 0, :2] = np.nan  # a failed trial of the both-camera objective
    both, left = summarise(p, samples)
    assert both.failed == 1 and left.failed == 0 and both.trials == 20
    assert np.isfinite([both.rot_rms, both.trans_rms, both.bound_rot, both.bound_trans]).all()
