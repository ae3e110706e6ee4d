"""Bad input to the estimator raises an error that names the problem — never a silent wrong pose."""

from __future__ import annotations

import numpy as np
import pytest
from estimate_scenes import noiseless

from mvpose_core.estimate import EstimateOptions, Observation, PoseInputError, estimate_pose
from mvpose_core.reasons import Reason
from mvpose_core.scene import ViewCamera
from mvpose_core.transforms import make_transform
from mvpose_core.uncertainty import cramer_rao_covariance, invert_information


def with_obs(obs: list[Observation], i: int, **change: object) -> list[Observation]:
    o = obs[i]
    fields = {"view": o.view, "camera_id": o.camera_id, "mark_id": o.mark_id, "uv": o.uv}
    fields.update(change)
    return obs[:i] + [Observation(**fields)] + obs[i + 1 :]  # type: ignore[arg-type]


def test_nan_pixel_is_named() -> None:
    obs, cams, marks, _ = noiseless("lab")
    bad = with_obs(obs, 2, uv=np.array([np.nan, 3.0]))
    with pytest.raises(PoseInputError, match=r"observation v1/right/M2: uv contains NaN") as e:
        estimate_pose(bad, cams, marks)
    assert e.value.reason is Reason.BAD_INPUT


def test_wrong_shapes_are_named() -> None:
    obs, cams, marks, _ = noiseless("lab")
    with pytest.raises(PoseInputError, match=r"v1/left/M2: uv must have shape \(2,\), got \(3,\)"):
        estimate_pose(with_obs(obs, 0, uv=np.zeros(3)), cams, marks)
    bad_marks = {**marks, "M4": np.array([1.0, 2.0])}
    with pytest.raises(PoseInputError, match=r"mark 'M4': position must be 3 finite values"):
        estimate_pose(obs, cams, bad_marks)
    with pytest.raises(ValueError, match="4x4"):
        cramer_rao_covariance(cams, marks, [o.key for o in obs], np.eye(3))


def test_too_few_marks() -> None:
    obs, cams, marks, _ = noiseless("lab")
    two = [o for o in obs if o.mark_id in ("M2", "M3")]
    with pytest.raises(PoseInputError, match=r"too few marks: .* got 2 \['M2', 'M3'\]") as e:
        estimate_pose(two, cams, marks)
    assert e.value.reason is Reason.TOO_FEW_MARKS
    with pytest.raises(PoseInputError, match="too few marks"):
        estimate_pose([], cams, marks)


def test_collinear_marks() -> None:
    obs, cams, marks, _ = noiseless("lab")
    line = {
        **marks,
        "M1": np.array([0.0, 0.0, 0.0]),
        "M2": np.array([100.0, 0.0, 0.0]),
        "M3": np.array([250.0, 0.0, 0.0]),
        "M4": np.array([-300.0, 0.0, 0.0]),
    }
    with pytest.raises(PoseInputError, match=r"collinear") as e:
        estimate_pose(obs, cams, line)
    assert e.value.reason is Reason.POSE_NOT_DETERMINED


def test_a_remembered_layout_is_checked_again_when_marks_or_cameras_change() -> None:
    # build_problem remembers the layout (cameras × marks) of recent calls; a trigger with the
    # same layout but new mark positions or new camera objects must not get the old one.
    obs, cams, marks, T = noiseless("lab")
    assert np.allclose(estimate_pose(obs, cams, marks).T_rf_from_pf, T, atol=1e-6)
    line = {m: np.array([100.0 * k, 0.0, 0.0]) for k, m in enumerate(sorted(marks))}
    with pytest.raises(PoseInputError, match=r"collinear"):
        estimate_pose(obs, cams, line)
    shifted = {m: p + np.array([0.0, 0.0, 5.0]) for m, p in marks.items()}
    moved = estimate_pose(obs, cams, shifted).T_rf_from_pf
    assert np.allclose(moved[:3, 3] + moved[:3, :3] @ [0.0, 0.0, 5.0], T[:3, 3], atol=1e-6)
    # The same cameras as new objects, one of them renamed: the old layout's index is not used.
    renamed = [ViewCamera(view=c.view, camera_id=c.camera_id + "x" if i == 0 else c.camera_id,
                          rig_position=c.rig_position, T_rf_from_cf=c.T_rf_from_cf,
                          model=c.model) for i, c in enumerate(cams)]
    with pytest.raises(PoseInputError, match=r"no camera v1/left in this station"):
        estimate_pose(obs, renamed, marks)


def test_mark_behind_a_camera() -> None:
    obs, cams, marks, T = noiseless("station1")
    # A camera turned around: whatever it reports, the mark it claims is behind it.
    c = cams[0]
    flipped = make_transform(
        c.T_rf_from_cf[:3, :3] @ np.diag([1.0, -1.0, -1.0]), c.T_rf_from_cf[:3, 3]
    )
    cams2 = [ViewCamera(c.view, c.camera_id, c.model, flipped, c.rig_id, c.rig_position), *cams[1:]]
    with pytest.raises(PoseInputError, match=r"behind camera v1/top_left") as e:
        estimate_pose(obs, cams2, marks, initial_T_rf_from_pf=T)
    assert e.value.reason in (Reason.MARK_BEHIND_CAMERA, Reason.POSE_NOT_DETERMINED)
    with pytest.raises(ValueError, match=r"mark 'T1' is behind camera v1/top_left"):
        cramer_rao_covariance(cams2, marks, [o.key for o in obs], T)


def test_unknown_camera_mark_and_duplicates() -> None:
    obs, cams, marks, _ = noiseless("lab")
    with pytest.raises(PoseInputError, match=r"no camera v3/left"):
        estimate_pose(with_obs(obs, 0, view=3), cams, marks)
    with pytest.raises(PoseInputError, match=r"unknown mark 'M9'"):
        estimate_pose(with_obs(obs, 0, mark_id="M9"), cams, marks)
    with pytest.raises(PoseInputError, match=r"observed twice"):
        estimate_pose(obs + [obs[0]], cams, marks)
    with pytest.raises(PoseInputError, match=r"sigma_px must be > 0, got -1"):
        estimate_pose(with_obs(obs, 1, sigma_px=-1.0), cams, marks)
    with pytest.raises(
        PoseInputError, match=r"sigma_px must be a positive number of pixels, got nan"
    ):
        estimate_pose(obs, cams, marks, sigma_px=float("nan"))


def test_undetermined_layout() -> None:
    obs, cams, marks, T = noiseless("lab")
    # left-only objective with the left camera of view 2 missing: marks M2, M3 only
    partial = [o for o in obs if not (o.view == 2 and o.camera_id == "left")]
    with pytest.raises(PoseInputError, match=r"too few marks for the left_only objective") as e:
        estimate_pose(partial, cams, marks, EstimateOptions(objective="left_only"))
    assert e.value.reason is Reason.TOO_FEW_MARKS
    # an information matrix with an unobservable direction (rotation about x) is refused
    J = np.random.default_rng(0).normal(size=(12, 6))
    J[:, 0] = 0.0
    with pytest.raises(ValueError, match="do not determine the pose"):
        invert_information(J.T @ J)


def test_bad_options_are_named() -> None:
    with pytest.raises(ValueError, match="objective must be"):
        EstimateOptions(objective="right_only")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="huber_px must be > 0, got 0"):
        EstimateOptions(huber_px=0.0)
    with pytest.raises(ValueError, match="outlier_px"):
        EstimateOptions(outlier_px=-2.0)


def test_3d_alignment_returns_a_rotation_even_for_mirrored_points() -> None:
    from mvpose_core.initial import align_points

    rng = np.random.default_rng(3)
    p = rng.normal(size=(6, 3)) * 100.0
    T = make_transform(np.linalg.qr(rng.normal(size=(3, 3)))[0] @ np.diag([1, 1, -1]),
                       [10.0, 20.0, 30.0])
    if np.linalg.det(T[:3, :3]) < 0:  # make it a proper rotation
        T[:3, :3] *= -1
    R, t = align_points(p, p @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-9)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-6)
    # A mirror image of the marks has no rotation onto it: the best proper one, det +1.
    R_m, _ = align_points(p, p * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(R_m) == pytest.approx(1.0) and np.allclose(R_m @ R_m.T, np.eye(3))
