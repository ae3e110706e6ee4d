"""The robot-driven hand-eye session on synthetic detections: each step's code, the hold-out
check and the calibration file it builds."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_core.calibration.session import HandEyeCode, HandEyeSession, SessionError
from mvpose_core.calibration.synthetic import CalibScene, make_scene, with_robot_error
from mvpose_core.transforms import (
    RobotConvention,
    make_transform,
    to_robot,
    transform_error,
    zyx_to_matrix,
)

CONV = RobotConvention.FANUC


@pytest.fixture(scope="module")
def scene() -> CalibScene:
    return make_scene(np.random.default_rng(7), n_poses=14, mount="robot", stereo=True)


def _session(scene: CalibScene, holdout: int = 3) -> HandEyeSession:
    return HandEyeSession("lab", "stereo", scene.board, CONV, dict(scene.cameras),
                          dict(scene.T_cfc_from_cf0), np.eye(4), holdout=holdout)


def _fill(session: HandEyeSession, scene: CalibScene, poses: dict, noise_px: float = 0.1,
          seed: int = 1) -> None:
    dets = scene.observe(np.random.default_rng(seed), noise_px)
    for sid, A in poses.items():
        session.add(to_robot(A, CONV), {c: dets[c][sid] for c in scene.cameras})


def _refused(code: HandEyeCode, fn, *args) -> str:  # type: ignore[no-untyped-def]
    with pytest.raises(SessionError) as err:
        fn(*args)
    assert err.value.code is code, err.value
    return str(err.value)


def test_session_solves_on_its_poses_and_checks_the_held_out_ones(scene: CalibScene) -> None:
    s = _session(scene)
    noisy = with_robot_error(np.random.default_rng(3), scene.robot_poses, 0.05, 0.01)
    _fill(s, scene, noisy)
    held = s.held_out()
    assert len(held) == 3 and len(set(held)) == 3
    out = s.calculate("tester")
    assert sorted(out.result.per_sample_rms_px) == sorted(set(s.samples) - set(held))
    deg, mm = transform_error(out.result.X, scene.X)
    assert mm < 0.5 and deg < 0.05, (mm, deg)
    assert sorted(out.holdout) == sorted(held)
    for h in out.holdout.values():  # a good result predicts poses it never saw, up to the
        assert h.rms_px < 3.0 and h.mm < 0.3 and h.deg < 0.08, h  # robot's own pose error
    wrong = s.samples[held[0]]  # a pose the robot did not take: the hold-out check sees it
    s.samples[held[0]] = type(wrong)(wrong.sid, wrong.values, wrong.T_rf_from_gf @ make_transform(
        np.eye(3), [2.0, 0.0, 0.0]), wrong.detections)
    assert s._check(out.result, s.samples[held[0]]).mm > 1.8
    calib = out.calibration
    assert calib.kind == "handeye" and calib.sha256 == calib.content_hash()
    assert set(calib.inputs.samples_rejected) >= set(held)
    assert calib.report["hold-out"][held[0]]["rms_px"] == out.holdout[held[0]].rms_px
    assert calib.rigs["stereo"].T_gf_from_rig is not None


def test_too_few_poses_and_a_board_not_found(scene: CalibScene) -> None:
    s = _session(scene)
    ids = list(scene.robot_poses)[:7]
    _fill(s, scene, {sid: scene.robot_poses[sid] for sid in ids})
    msg = _refused(HandEyeCode.TOO_FEW_POSES, s.calculate)
    assert "7 poses" in msg and "at least 8" in msg
    first = scene.robot_poses[ids[0]]
    msg = _refused(HandEyeCode.BOARD_NOT_FOUND, s.add, to_robot(first, CONV),
                   {c: None for c in scene.cameras})
    assert "pose 008" in msg and "not found" in msg
    assert len(s.samples) == 7  # the refused pose is not kept


def test_units_are_checked_per_pose_and_over_the_session(scene: CalibScene) -> None:
    s = _session(scene)
    A = next(iter(scene.robot_poses.values()))
    metres = to_robot(A, CONV)
    metres[:3] /= 1000.0
    assert "wrong unit" in _refused(HandEyeCode.UNIT_SUSPICIOUS, s.add, metres, {})
    _refused(HandEyeCode.BAD_POSE, s.add, [1.0, 2.0], {})
    _refused(HandEyeCode.BAD_POSE, s.add, None, {})
    radians = _session(scene)
    dets = scene.observe(np.random.default_rng(1), 0.1)
    for sid, A in scene.robot_poses.items():
        v = to_robot(A, CONV)
        v[3:] = np.radians(v[3:])  # a program that sends radians
        radians.add(v, {c: dets[c][sid] for c in scene.cameras})
    assert "radians" in _refused(HandEyeCode.UNIT_SUSPICIOUS, radians.calculate)


def test_rotations_about_one_axis_are_refused(scene: CalibScene) -> None:
    s = _session(scene, holdout=0)
    A0 = next(iter(scene.robot_poses.values()))
    poses = {f"{k:03d}": A0 @ make_transform(zyx_to_matrix(6.0 * k, 0.0, 0.0),
                                            [20.0 * k, -10.0 * k, 5.0 * k])
             for k in range(6)}
    flat = CalibScene("robot", scene.board, scene.cameras, scene.T_cfc_from_cf0, scene.X,
                      scene.Y, poses)
    _fill(s, flat, poses)
    assert "one axis" in _refused(HandEyeCode.TOO_LITTLE_ROTATION, s.calculate)


def test_poses_of_another_convention_do_not_fit(scene: CalibScene) -> None:
    s = _session(scene)
    dets = scene.observe(np.random.default_rng(1), 0.1)
    for sid, A in scene.robot_poses.items():
        # a KUKA program's A, B, C sent as FANUC W, P, R
        s.add(to_robot(A, RobotConvention.KUKA), {c: dets[c][sid] for c in scene.cameras})
    with pytest.raises(SessionError) as err:
        s.calculate()
    assert err.value.code in (HandEyeCode.POSES_DO_NOT_FIT, HandEyeCode.OUTLIERS,
                              HandEyeCode.TOO_LITTLE_ROTATION), err.value


def test_a_board_declared_one_percent_small_is_refused(scene: CalibScene) -> None:
    from mvpose_core.calibration.boards import BoardSpec

    b = scene.board
    small = BoardSpec.parse(f"{b.kind}:{b.cols}x{b.rows}:{b.square_mm * 0.99:.4f}")
    s = HandEyeSession("lab", "stereo", small, CONV, dict(scene.cameras),
                       dict(scene.T_cfc_from_cf0), np.eye(4))
    _fill(s, scene, scene.robot_poses)
    assert "declared size" in _refused(HandEyeCode.BOARD_SCALE, s.calculate)


def test_a_pose_recorded_at_the_wrong_moment_is_left_out(scene: CalibScene) -> None:
    s = _session(scene, holdout=0)
    poses = with_robot_error(np.random.default_rng(4), scene.robot_poses, 0.05, 0.01)
    bad = sorted(poses)[4]
    poses[bad] = poses[bad] @ make_transform(zyx_to_matrix(0.0, 0.3, 0.0), [3.0, -2.0, 0.0])
    _fill(s, scene, poses)
    out = s.calculate()
    assert bad in out.result.left_out and bad not in out.result.per_sample_rms_px
    assert any(bad in w for w in out.report.warnings)
