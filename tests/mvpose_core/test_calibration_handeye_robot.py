"""The hand-eye with a real robot's pose errors (issue 26): accuracy against a bundle adjustment
weighted with the true σ and against the closed forms, an honest 1σ over Monte Carlo sets, and
the refusals (a board of the wrong size, outlier samples, poses that do not fit)."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import pytest

from mvpose_core.calibration.boards import BoardSpec
from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.handeye import (
    HandEyeOptions,
    HandEyeResult,
    build_problem,
    calibrate_handeye,
)
from mvpose_core.calibration.intrinsics import calibrate_intrinsics
from mvpose_core.calibration.joint import HandEyeProblem, Weights, refine
from mvpose_core.calibration.synthetic import CalibScene, make_scene, with_robot_error
from mvpose_core.transforms import Array, make_transform, matrix_to_rotvec, transform_error

# The issue's sets: 15 × 11 ChArUco squares of 40 mm, a 2048² camera at about 1.7 m, 18 flange
# poses rotated about several axes, 0.1 px corners, a good robot (0.05 mm / 0.01° per axis).
BOARD = BoardSpec.parse("charuco:15x11:40:30")
ROBOT_MM, ROBOT_DEG, NOISE_PX = 0.05, 0.01, 0.1
N_SETS = 10


@dataclass(frozen=True)
class Trial:
    scene: CalibScene
    problem: HandEyeProblem
    result: HandEyeResult
    reference: Array  # X of the adjustment weighted with the true σ (not estimated)


def _issue_set(rng: np.random.Generator, n_poses: int = 18) -> tuple[CalibScene, HandEyeProblem]:
    scene = make_scene(rng, n_poses=n_poses, stereo=False, board=BOARD, distance_mm=(1550, 1850))
    det = scene.observe(rng, NOISE_PX)
    true = scene.cameras["left"]
    # The intrinsics step first, on the same images, as `mvpose calibrate handeye` runs it.
    cam = calibrate_intrinsics("left", det["left"], BOARD, (true.width, true.height)).camera
    poses = with_robot_error(rng, scene.robot_poses, ROBOT_MM, ROBOT_DEG)
    problem, rejected = build_problem("robot", BOARD, {"left": cam}, poses, det)
    assert rejected == {}
    return scene, problem


@pytest.fixture(scope="module")
def trials() -> list[Trial]:
    rng = np.random.default_rng(2026)
    out = []
    for _ in range(N_SETS):
        scene, problem = _issue_set(rng)
        result = calibrate_handeye(problem)
        ref = refine(
            problem, result.X, result.Y, weights=Weights(NOISE_PX, ROBOT_MM, ROBOT_DEG),
            estimate=False, intrinsics=True,
        )  # fmt: skip
        out.append(Trial(scene, problem, result, ref.X))
    return out


def _errors(Xs: list[Array], trials: list[Trial]) -> Array:
    """(mm, deg) of each estimate against the truth."""
    return np.array([transform_error(X, t.scene.X)[::-1] for X, t in zip(Xs, trials, strict=True)])


def _rms(e: Array) -> Array:
    return np.sqrt(np.mean(np.square(e), axis=0))


def test_as_good_as_the_weighted_adjustment_and_better_than_the_closed_forms(trials) -> None:
    ours = _errors([t.result.X for t in trials], trials)
    reference = _errors([t.reference for t in trials], trials)
    closed = np.array(
        [
            [
                min(
                    transform_error(t.result.methods[m].T, t.scene.X)[::-1][k]
                    for m in ("tsai", "park")
                )
                for k in (0, 1)
            ]
            for t in trials
        ]
    )
    assert np.all(_rms(ours) <= 1.5 * _rms(reference)), (_rms(ours), _rms(reference))
    # Never clearly worse than the better of Tsai and Park (chosen with the truth), set by set.
    assert np.all(ours <= 1.5 * closed), np.c_[ours, closed]
    # The issue's sets: the closed forms are 0.12–0.23 mm from the truth, the adjustment with
    # robot poses as measurements well under them.
    assert _rms(ours)[0] < 0.6 * _rms(closed)[0], (_rms(ours), _rms(closed))
    # The intrinsics do not absorb the robot's error: fx stays within its own 1σ range.
    for t in trials:
        fx, sfx = t.result.cameras["left"].fx, t.result.camera_sigma["left"][0]
        assert abs(fx - t.scene.cameras["left"].fx) < 4 * sfx


def test_reported_sigma_is_the_actual_error_over_monte_carlo_sets(trials) -> None:
    """Actual RMS error over the sets / the reported 1σ (RSS, shown first in the report) within
    0.7–1.4; and the stricter check the 6-DoF covariance allows: the mean squared Mahalanobis
    distance of X is χ² with 6·N degrees of freedom over 6·N, so its square root lies within
    1 ± 3/√(12·N) (±0.27 for N = 10) when the covariance is right."""
    err = _errors([t.result.X for t in trials], trials)
    sig = np.array([[t.result.sigma_mm, t.result.sigma_deg] for t in trials])
    ratio = _rms(err) / np.sqrt(np.mean(np.square(sig), axis=0))
    assert np.all(ratio > 0.7) and np.all(ratio < 1.4), ratio
    d2 = []
    for t in trials:
        X, T = t.result.X, t.scene.X
        delta = np.r_[matrix_to_rotvec(X[:3, :3] @ T[:3, :3].T), X[:3, 3] - T[:3, 3]]
        d2.append(delta @ np.linalg.solve(t.result.cov[:6, :6], delta))
    m = float(np.sqrt(np.mean(d2) / 6.0))
    assert abs(m - 1.0) < 3.0 / np.sqrt(12.0 * N_SETS), m
    # The robot's σ is found in the data: near the true one.
    w = np.array([[t.result.weights.robot_mm, t.result.weights.robot_deg] for t in trials])
    assert np.all(np.abs(w.mean(axis=0) / [ROBOT_MM, ROBOT_DEG] - 1.0) < 0.3), w.mean(axis=0)


def test_closed_forms_are_not_reported_as_disagreeing_when_the_sigma_explains_them(trials) -> None:
    for t in trials:
        assert all(c.status == "ok" for c in t.result.methods.values()), t.result.methods


# --------------------------------------------------------------------------- refusals


def test_a_board_one_percent_smaller_than_printed_is_refused() -> None:
    rng = np.random.default_rng(11)
    scene, problem = _issue_set(rng, n_poses=12)
    declared = BoardSpec.parse("charuco:15x11:39.6:29.7")  # the print is 1 % larger
    wrong = HandEyeProblem(
        "robot", declared, problem.cameras, problem.T_cfc_from_cf0, problem.robot_poses,
        problem.detections,
    )  # fmt: skip
    says = r"the robot motion says the board is 1\.0(09|10)\d* ± 0\.000\d+ \(1σ\) times its"
    with pytest.raises(CalibrationError, match=says):
        calibrate_handeye(wrong)
    # The right size passes, and the scale it found is 1 within its 3σ.
    ok = calibrate_handeye(problem)
    assert abs(ok.scale - 1.0) < 3 * ok.scale_sigma


def test_outlier_samples_are_left_out_and_named_or_the_solve_refused() -> None:
    rng = np.random.default_rng(12)
    scene, problem = _issue_set(rng, n_poses=14)
    poses = dict(problem.robot_poses)
    # 006: its robot pose recorded at the wrong moment (10 mm off); 011: a blurred image.
    poses["006"] = poses["006"] @ make_transform(np.eye(3), [10.0, 0.0, 0.0])
    dets = {s: dict(d) for s, d in problem.detections.items()}
    d = dets["011"]["left"]
    dets["011"]["left"] = type(d)(d.ids, d.uv + rng.normal(0.0, 2.0, d.uv.shape))
    bad = HandEyeProblem(
        "robot", BOARD, problem.cameras, problem.T_cfc_from_cf0, poses, dets
    )  # fmt: skip
    res = calibrate_handeye(bad)
    assert sorted(res.left_out) == ["006", "011"]
    assert re.search(r"robot pose off the fit by \d+\.\d+ mm", res.left_out["006"])
    assert res.left_out["011"].startswith("reprojection RMS")
    assert "006" not in res.per_sample_rms_px and "011" not in res.per_sample_rms_px
    assert transform_error(res.X, scene.X)[1] < 1.0
    assert any("left out outlier samples 006" in w for w in res.warnings)
    with pytest.raises(
        CalibrationError, match=r"too few samples left .* 12 remain, need at least 13"
    ):
        calibrate_handeye(bad, HandEyeOptions(min_samples=13))
