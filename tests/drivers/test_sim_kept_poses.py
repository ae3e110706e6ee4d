"""A simulated scene keeps the renderings of its recent part poses when asked to (the station
benchmark moves its served part over a cycle of places without rendering while it measures)."""

from __future__ import annotations

import numpy as np
import pytest
from camera_scenes import small_station

from drivers.cameras import SimScene
from mvpose_core.station import StationConfig
from mvpose_core.transforms import xyzwpr_to_matrix


def _poses(station_name: str) -> tuple[StationConfig, list[np.ndarray]]:
    station = small_station(station_name)
    T0 = station.recipe().T_rf_from_pf0.matrix
    return station, [T0 @ xyzwpr_to_matrix([d, -d, 0.0, 0.0, 0.0, d / 10]) for d in (0.0, 5.0,
                                                                                     10.0)]


def test_a_kept_pose_comes_back_without_rendering_and_the_oldest_is_dropped() -> None:
    station, (a, b, c) = _poses("station1")
    scene = SimScene(station, None, np.random.default_rng(0), keep_poses=2)
    cid = station.cameras[0].id
    scene.set_part_pose(a)
    first_a = scene.frame(cid)
    scene.set_part_pose(b)
    first_b = scene.frame(cid)
    assert first_b is not first_a
    scene.set_part_pose(a)  # kept: the same frame (a rendering draws its noise again)
    assert scene.frame(cid) is first_a
    np.testing.assert_array_equal(scene.T_rf_from_pf, a)
    assert scene.truth(cid).image is first_a
    scene.set_part_pose(c)  # three poses, two kept: b (the least recent) is dropped
    scene.set_part_pose(b)  # rendered again, kept; a (now the least recent) is dropped
    assert scene.frame(cid) is not first_b
    scene.set_part_pose(a)
    assert scene.frame(cid) is not first_a


def test_without_kept_poses_every_move_renders() -> None:
    station, (a, _b, _c) = _poses("station1")
    scene = SimScene(station, None, np.random.default_rng(0))
    cid = station.cameras[0].id
    scene.set_part_pose(a)
    first = scene.frame(cid)
    scene.set_part_pose(a)
    assert scene.frame(cid) is not first


def test_a_negative_number_of_kept_poses_is_refused() -> None:
    station = small_station("station1")
    with pytest.raises(ValueError, match="keep_poses must be >= 0, got -1"):
        SimScene(station, None, np.random.default_rng(0), keep_poses=-1)
