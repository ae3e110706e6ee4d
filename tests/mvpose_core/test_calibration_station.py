"""Fixed stations: cameras related from images alone, then placed rigidly in the robot frame."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.handeye import mean_transform
from mvpose_core.calibration.intrinsics import board_pose
from mvpose_core.calibration.station import calibrate_station
from mvpose_core.calibration.synthetic import make_station_scene
from mvpose_core.transforms import (
    compose,
    invert,
    make_transform,
    rotvec_to_matrix,
    transform_error,
)


def _noisy_rf_poses(scene, rng, mm: float, deg: float) -> dict:
    """Board poses in RF as a robot or a pointer measures them: each placement a little off."""
    return {
        s: compose(
            T,
            make_transform(
                rotvec_to_matrix(rng.normal(0, np.radians(deg), 3)), rng.normal(0, mm, 3)
            ),
        )
        for s, T in scene.T_rf_from_bf.items()
    }


def _relative(T: dict, a: str, b: str):
    return compose(invert(T[a]), T[b])


@pytest.fixture(scope="module")
def station():
    rng = np.random.default_rng(12)
    scene = make_station_scene(rng, n_placements=12)
    return scene, scene.observe(rng, 0.1), _noisy_rf_poses(scene, rng, 0.5, 0.05)


def test_robot_error_does_not_bend_the_station(station) -> None:
    scene, det, rf = station
    # The true intrinsics, held: this is about the robot frame, not the camera model.
    res = calibrate_station(scene.board, scene.cameras, det, rf, refine_intrinsics=False)
    assert len(res.groups) == 1
    naive = {}
    for c, cam in scene.cameras.items():
        # Each camera on its own from the RF measurements: what we avoid.
        naive[c] = mean_transform(
            [
                compose(rf[s], invert(board_pose(cam, d, scene.board)))
                for s, d in det[c].items()
                if d
            ]
        )
    truth = scene.T_rf_from_cf
    ours = transform_error(
        _relative(res.T_rf_from_cf, "cam1", "cam3"), _relative(truth, "cam1", "cam3")
    )
    theirs = transform_error(_relative(naive, "cam1", "cam3"), _relative(truth, "cam1", "cam3"))
    assert ours[1] < 0.2 and ours[0] < 0.01, ours
    assert theirs[1] > 3 * ours[1]
    for c in scene.cameras:
        deg, mm = transform_error(res.T_rf_from_cf[c], truth[c])
        assert mm < 2.0 and deg < 0.1  # the absolute placement averages all placements
    assert 0.2 < res.placement_rms_mm["cam1"] < 2.0  # reports the RF measurement scatter


def test_exact_data_gives_the_truth() -> None:
    rng = np.random.default_rng(2)
    scene = make_station_scene(rng, n_placements=8)
    res = calibrate_station(scene.board, scene.cameras, scene.observe(rng, 0.0), scene.T_rf_from_bf)
    for c in scene.cameras:
        deg, mm = transform_error(res.T_rf_from_cf[c], scene.T_rf_from_cf[c])
        assert mm < 1e-3 and deg < 1e-5


def test_cameras_without_shared_views_form_separate_groups(station) -> None:
    scene, det, rf = station
    # Keep only placements cam3 sees alone, and drop cam3 from all the others.
    det = {c: dict(d) for c, d in det.items()}
    for s in det["cam3"]:
        if det["cam3"][s] is not None:
            det["cam1"][s] = None
            det["cam2"][s] = None
    res = calibrate_station(scene.board, scene.cameras, det, rf)
    groups = sorted(sorted(g.T_ref_from_cf) for g in res.groups)
    assert groups == [["cam1", "cam2"], ["cam3"]]
    assert transform_error(res.T_rf_from_cf["cam3"], scene.T_rf_from_cf["cam3"])[1] < 3.0


def test_camera_that_never_sees_the_board(station) -> None:
    scene, det, rf = station
    det = {c: dict(d) for c, d in det.items()}
    det["cam2"] = dict.fromkeys(det["cam2"])
    with pytest.raises(CalibrationError, match="camera 'cam2'.*not found in any"):
        calibrate_station(scene.board, scene.cameras, det, rf)
