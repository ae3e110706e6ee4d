"""Synthetic observations and displacements: what the simulation studies and the demo build on."""

from __future__ import annotations

import numpy as np
import pytest
from estimate_scenes import station

from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import make_transform, matrix_to_xyzwpr


def test_random_displacement_stays_in_its_box() -> None:
    rng = np.random.default_rng(0)
    v = np.array([matrix_to_xyzwpr(random_displacement(rng, 100.0, 10.0)) for _ in range(500)])
    assert np.all(np.abs(v[:, :3]) <= 100.0) and np.all(np.abs(v[:, 3:]) <= 10.0 + 1e-9)
    assert np.all(np.abs(v).max(axis=0) > [90, 90, 90, 9, 9, 9])  # and fills it
    # same seed, same draws; no hidden global RNG
    a = random_displacement(np.random.default_rng(3), 5.0, 1.0)
    assert np.array_equal(a, random_displacement(np.random.default_rng(3), 5.0, 1.0))
    with pytest.raises(ValueError, match="max_mm"):
        random_displacement(rng, -1.0, 1.0)


def test_observations_follow_the_sightings_with_the_requested_noise() -> None:
    st, rec, _, _ = station("lab")
    T = rec.T_rf_from_pf0.matrix
    clean = synthetic_observations(st, rec, T, np.random.default_rng(1), 0.0)
    assert sorted(o.key for o in clean) == sorted(
        (s.view, s.camera, m) for s in rec.sightings for m in s.marks
    )
    rng = np.random.default_rng(2)
    diffs = np.concatenate([
        np.array([o.uv for o in synthetic_observations(st, rec, T, rng, 0.7)])
        - np.array([o.uv for o in clean])
        for _ in range(200)
    ])  # fmt: skip
    assert abs(diffs.std() - 0.7) < 0.03 and abs(diffs.mean()) < 0.03


def test_marks_outside_the_image_or_behind_the_camera_are_refused() -> None:
    st, rec, _, _ = station("station1")
    T = rec.T_rf_from_pf0.matrix
    shifted = make_transform(np.eye(3), [0.0, 600.0, 0.0]) @ T
    with pytest.raises(ValueError, match=r"falls outside camera v1/\w+ at"):
        synthetic_observations(st, rec, shifted, np.random.default_rng(0), 0.1)
    assert synthetic_observations(st, rec, shifted, np.random.default_rng(0), 0.1,
                                  require_in_image=False)  # fmt: skip
    behind = make_transform(np.eye(3), [0.0, 0.0, 3000.0]) @ T  # part lifted above the cameras
    with pytest.raises(ValueError, match="behind the camera"):
        synthetic_observations(st, rec, behind, np.random.default_rng(0), 0.1)
    with pytest.raises(ValueError, match="sigma_px"):
        synthetic_observations(st, rec, T, np.random.default_rng(0), -1.0)
