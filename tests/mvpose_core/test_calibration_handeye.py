"""Intrinsics, stereo and hand-eye on synthetic detections with known truth (issue 5 acceptance)."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.handeye import (
    HandEyeOptions,
    board_pose_from_points,
    build_problem,
    calibrate_handeye,
    refine,
)
from mvpose_core.calibration.intrinsics import calibrate_intrinsics
from mvpose_core.calibration.stereo import calibrate_stereo
from mvpose_core.calibration.synthetic import make_scene
from mvpose_core.transforms import (
    apply,
    compose,
    invert,
    make_transform,
    transform_error,
    zyx_to_matrix,
)


@pytest.fixture(scope="module")
def lab() -> tuple:
    """15 robot poses, stereo rig on the flange, 0.1 px detector noise."""
    rng = np.random.default_rng(2024)
    scene = make_scene(rng, n_poses=15, mount="robot", stereo=True)
    return scene, scene.observe(rng, 0.1)


def test_chain_intrinsics_stereo_handeye_meets_acceptance(lab) -> None:
    scene, det = lab
    true = scene.cameras["left"]
    size = (true.width, true.height)
    left = calibrate_intrinsics("left", det["left"], scene.board, size)
    right = calibrate_intrinsics("right", det["right"], scene.board, size)
    for res in (left, right):
        assert abs(res.camera.fx / true.fx - 1) < 1e-3
        assert abs(res.camera.fy / true.fy - 1) < 1e-3
        assert sorted(res.per_sample_rms_px) == sorted(scene.robot_poses)
    st = calibrate_stereo(
        "left", "right", det["left"], det["right"], scene.board, left.camera, right.camera
    )
    true_baseline = float(np.linalg.norm(scene.T_cfc_from_cf0["right"][:3, 3]))
    assert abs(st.baseline_mm - true_baseline) < 0.1
    for m in (st.model1, st.model2):
        assert abs(m.fx / true.fx - 1) < 1e-3
    cams = {"left": st.model1, "right": st.model2}
    problem, rejected = build_problem(
        "robot", scene.board, cams, scene.robot_poses, det, {"right": st.T_cf2_from_cf1}
    )
    assert rejected == {}
    he = calibrate_handeye(problem)
    deg, mm = transform_error(he.X, scene.X)
    assert mm < 0.2 and deg < 0.02, (deg, mm)
    assert all(c.status == "ok" for c in he.methods.values()), he.methods
    assert 0.07 < he.sigma_px < 0.13  # 0.1 px per coordinate, estimated from the residuals
    for cid, m in he.cameras.items():  # intrinsics refined with the robot poses
        assert abs(m.fx / true.fx - 1) < 1e-3, cid
    refined_baseline = float(np.linalg.norm(he.T_cfc_from_cf0["right"][:3, 3]))
    assert abs(refined_baseline - true_baseline) < 0.1


def test_reported_sigma_matches_spread_over_trials() -> None:
    rng = np.random.default_rng(99)
    scene = make_scene(rng, n_poses=15, mount="robot", stereo=False)
    errs, sig = [], []
    for _ in range(20):
        det = scene.observe(rng, 0.1)
        problem, _ = build_problem("robot", scene.board, scene.cameras, scene.robot_poses, det)
        he = calibrate_handeye(problem)
        errs.append(transform_error(he.X, scene.X))
        sig.append((he.sigma_deg, he.sigma_mm))
    rms = np.sqrt(np.mean(np.square(errs), axis=0))
    reported = np.mean(sig, axis=0)
    ratio = rms / reported
    assert np.all(ratio > 1 / 1.5) and np.all(ratio < 1.5), (rms, reported)


def test_fixed_camera_with_board_on_flange() -> None:
    rng = np.random.default_rng(5)
    scene = make_scene(rng, n_poses=12, mount="fixed", stereo=False)
    det = scene.observe(rng, 0.1)
    problem, _ = build_problem("fixed", scene.board, scene.cameras, scene.robot_poses, det)
    he = calibrate_handeye(problem)
    deg, mm = transform_error(he.X, scene.X)
    assert mm < 0.2 and deg < 0.02
    assert transform_error(he.Y, scene.Y)[1] < 0.3


def test_refinement_sits_at_truth_without_noise_and_converges_from_offsets() -> None:
    rng = np.random.default_rng(3)
    scene = make_scene(rng, n_poses=8, mount="robot", stereo=False)
    det = scene.observe(rng, 0.0)
    problem, _ = build_problem("robot", scene.board, scene.cameras, scene.robot_poses, det)
    at_truth = refine(problem, scene.X, scene.Y)
    assert max(np.abs(r).max() for r in at_truth.residuals.values()) < 1e-6
    off = compose(scene.X, make_transform(zyx_to_matrix(0.5, -0.4, 0.3), [3.0, -2.0, 4.0]))
    r = refine(problem, off, scene.Y)
    deg, mm = transform_error(r.X, scene.X)
    assert deg < 1e-6 and mm < 1e-5


def test_paper_method_board_measured_in_robot_frame() -> None:
    rng = np.random.default_rng(8)
    scene = make_scene(rng, n_poses=8, mount="robot", stereo=False)
    det = scene.observe(rng, 0.1)
    # Touch four board corners with a pointer: 0.05 mm measurement noise.
    ids = [
        0,
        scene.board.cols - 1,
        scene.board.n_corners - scene.board.cols,
        scene.board.n_corners - 1,
    ]
    p_rf = apply(scene.Y, scene.board.object_points[ids]) + rng.normal(0, 0.05, (4, 3))
    T_rf_from_bf, rms = board_pose_from_points(scene.board, ids, p_rf)
    assert rms < 0.2
    problem, _ = build_problem("robot", scene.board, scene.cameras, scene.robot_poses, det)
    exact = HandEyeOptions(robot_sigma_mm=0.001, robot_sigma_deg=0.0001)  # a simulated robot
    he = calibrate_handeye(problem, exact, T_rf_from_bf=T_rf_from_bf)
    paper = he.methods["paper_eq10"]
    assert paper.T is not None
    assert transform_error(paper.T, scene.X)[1] < 1.0
    assert transform_error(he.X, scene.X)[1] < 0.2


def test_missing_board_is_left_out_by_id_not_shifted(lab) -> None:
    scene, det = lab
    det = {c: dict(d) for c, d in det.items()}
    det["left"]["005"] = None
    det["right"]["005"] = None
    problem, rejected = build_problem(
        "robot", scene.board, scene.cameras, scene.robot_poses, det, scene.T_cfc_from_cf0
    )
    assert rejected == {"005": "left: board not found; right: board not found"}
    assert "005" not in problem.detections
    he = calibrate_handeye(problem)
    assert "005" not in he.per_sample_rms_px
    # Every other sample keeps its own robot pose: a shift would blow the residuals up.
    assert max(he.per_sample_rms_px.values()) < 0.3
    assert transform_error(he.X, scene.X)[1] < 0.2


# --------------------------------------------------------------------------- degenerate input


def _problem(scene, det, poses=None):
    return build_problem("robot", scene.board, scene.cameras, poses or scene.robot_poses, det)[0]


def test_too_few_poses() -> None:
    rng = np.random.default_rng(1)
    scene = make_scene(rng, n_poses=3, stereo=False)
    with pytest.raises(CalibrationError, match="too few usable samples: 3"):
        calibrate_handeye(_problem(scene, scene.observe(rng, 0.1)))


def test_pure_translations() -> None:
    rng = np.random.default_rng(1)
    scene = make_scene(rng, n_poses=6, stereo=False)
    first = next(iter(scene.robot_poses.values()))
    poses = {
        sid: make_transform(first[:3, :3], first[:3, 3] + rng.normal(0, 40, 3))
        for sid in scene.robot_poses
    }
    moved = type(scene)(
        scene.mount, scene.board, scene.cameras, scene.T_cfc_from_cf0, scene.X, scene.Y, poses
    )
    det = moved.observe(rng, 0.1)
    with pytest.raises(CalibrationError, match="pure translations"):
        calibrate_handeye(_problem(moved, det))


def test_mismatched_counts_name_the_ids(lab) -> None:
    scene, det = lab
    poses = dict(scene.robot_poses)
    del poses["003"]
    with pytest.raises(CalibrationError, match=r"images without a pose: \['003'\]"):
        build_problem("robot", scene.board, scene.cameras, poses, det, scene.T_cfc_from_cf0)


def test_board_never_found(lab) -> None:
    scene, det = lab
    det = {c: dict.fromkeys(d) for c, d in det.items()}
    with pytest.raises(CalibrationError, match="board was not found in any of the 15 images"):
        build_problem(
            "robot", scene.board, scene.cameras, scene.robot_poses, det, scene.T_cfc_from_cf0
        )


def test_robot_poses_in_metres() -> None:
    rng = np.random.default_rng(4)
    scene = make_scene(rng, n_poses=8, stereo=False)
    det = scene.observe(rng, 0.1)
    metres = {
        sid: make_transform(A[:3, :3], A[:3, 3] / 1000.0) for sid, A in scene.robot_poses.items()
    }
    with pytest.raises(CalibrationError, match="wrong unit"):
        calibrate_handeye(_problem(scene, det, metres))


def test_inverted_robot_poses_are_caught_by_the_cross_check() -> None:
    """Poses exported as T_gf_from_rf by mistake: no calibration comes out of it."""
    rng = np.random.default_rng(6)
    scene = make_scene(rng, n_poses=10, stereo=False)
    det = scene.observe(rng, 0.1)
    wrong = {sid: invert(A) for sid, A in scene.robot_poses.items()}
    with pytest.raises(CalibrationError, match="robot poses do not fit the images"):
        calibrate_handeye(_problem(scene, det, wrong))


def test_rotations_about_one_axis_only() -> None:
    from mvpose_core.calibration.robotposes import check_motion

    base = make_transform(zyx_to_matrix(0.0, 0.0, 180.0), [1200.0, 0.0, 900.0])
    poses = {
        f"{k:03d}": compose(
            base, make_transform(zyx_to_matrix(15.0 * k, 0.0, 0.0), [30.0 * k, 0, 0])
        )
        for k in range(6)
    }
    cams = {sid: invert(A) for sid, A in poses.items()}  # any camera motion of similar size
    with pytest.raises(CalibrationError, match="every robot rotation is about one axis"):
        check_motion(poses, cams, "hand-eye")


def test_board_carried_by_the_robot_places_a_fixed_station() -> None:
    """Eye-to-hand on one camera gives the board on the flange; the station follows from it."""
    from mvpose_core.calibration.station import board_poses_from_robot, calibrate_station
    from mvpose_core.calibration.synthetic import make_station_scene

    rng = np.random.default_rng(17)
    scene = make_station_scene(rng, n_placements=12)
    T_gf_from_bf = make_transform(zyx_to_matrix(0.0, 0.0, 180.0), [-100.0, -80.0, 120.0])
    robot = {s: compose(T, invert(T_gf_from_bf)) for s, T in scene.T_rf_from_bf.items()}
    det = scene.observe(rng, 0.1)
    best = max(det, key=lambda c: sum(d is not None for d in det[c].values()))
    problem, _ = build_problem(
        "fixed", scene.board, {best: scene.cameras[best]}, robot, {best: det[best]}
    )
    he = calibrate_handeye(problem)
    assert transform_error(he.Y, T_gf_from_bf)[1] < 0.5
    res = calibrate_station(
        scene.board,
        scene.cameras,
        det,
        board_poses_from_robot(robot, he.Y),
        refine_intrinsics=False,  # the true intrinsics: this is about the placement in RF
    )
    for c in scene.cameras:
        deg, mm = transform_error(res.T_rf_from_cf[c], scene.T_rf_from_cf[c])
        assert mm < 0.5 and deg < 0.02, (c, deg, mm)


def test_nan_and_implausible_solver_answers_are_screened_out() -> None:
    from mvpose_core.calibration.handeye import screen, solve_axxb

    rng = np.random.default_rng(1)
    scene = make_scene(rng, n_poses=6, stereo=False)
    ids = sorted(scene.robot_poses)
    chains = [invert(scene.robot_poses[s]) for s in ids]
    boards = [scene.T_cf_from_bf("left", s) for s in ids]
    assert transform_error(solve_axxb(chains, boards, "park"), scene.X)[1] < 1e-6
    boards[2] = boards[2].copy()
    boards[2][0, 3] = np.nan  # one corrupt board pose
    assert solve_axxb(chains, boards, "tsai") is None
    far = make_transform(np.eye(3), [0.0, 0.0, 5000.0])
    checks, plausible = screen({"a": None, "b": far, "c": scene.X}, "robot", HandEyeOptions())
    assert checks["a"].status == "NaN"
    assert checks["b"].status == "implausible: camera 5000 mm from the flange"
    assert list(plausible) == ["c"]
    # A fixed camera 5 m from the robot base is normal in a body shop.
    assert "b" in screen({"b": far}, "fixed", HandEyeOptions())[1]


def test_charuco_partial_views_calibrate_by_corner_id() -> None:
    from mvpose_core.calibration.boards import BoardSpec

    rng = np.random.default_rng(31)
    board = BoardSpec.parse("charuco:12x9:30:22")
    # Close views: the board runs off the image, so many views hold only some corners.
    scene = make_scene(rng, n_poses=12, stereo=False, board=board, distance_mm=(380.0, 480.0))
    det = scene.observe(rng, 0.1)["left"]
    partial = [s for s, d in det.items() if d is not None and len(d) < board.n_corners]
    assert partial, "the scene should contain partial views"
    true = scene.cameras["left"]
    res = calibrate_intrinsics("left", det, board, (true.width, true.height))
    assert abs(res.camera.fx / true.fx - 1) < 1e-3
    assert res.rms_px < 0.2


def test_stereo_needs_the_same_samples_in_both_cameras(lab) -> None:
    scene, det = lab
    right = dict(det["right"])
    del right["002"]
    cam = scene.cameras["left"]
    with pytest.raises(CalibrationError, match=r"only 'left': \['002'\]"):
        calibrate_stereo("left", "right", det["left"], right, scene.board, cam, cam)
