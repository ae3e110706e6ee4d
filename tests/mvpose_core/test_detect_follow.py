"""A displaced part's windows predicted from the pose of the blobs its small windows held."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mvpose_core.detect import DetectOptions, detect_marks_many
from mvpose_core.detect.follow import pose_from_blobs
from mvpose_core.detect.window import _search, _unfound
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.scene import view_cameras
from mvpose_core.station import load_station
from mvpose_core.transforms import rotvec_to_matrix

STATION1 = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"


@pytest.fixture(scope="module")
def station1():  # type: ignore[no-untyped-def]
    station = load_station(STATION1)
    return view_cameras(station), station.recipe()


def _displaced(recipe, share: float):  # type: ignore[no-untyped-def]
    """The reference pose rotated by ``share`` of the tolerance about the marks' centroid and
    moved by ``share`` of it (the directions of bench/bench_displaced.py)."""
    tol = recipe.tolerances
    axis = np.array([0.5, -0.4, 0.75])
    R = rotvec_to_matrix(np.deg2rad(share * tol.max_offset_deg) * axis / np.linalg.norm(axis))
    c = np.asarray(recipe.mark_centroid(), dtype=float)
    move = np.array([0.7, -0.6, 0.4])
    D = np.eye(4)
    D[:3, :3] = R
    D[:3, 3] = share * tol.max_offset_mm * move / np.linalg.norm(move) + c - R @ c
    return recipe.T_rf_from_pf0.matrix @ D


def _frames(cams, recipe, T, clutter: bool):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(7)
    return [(render_view(c, recipe, T, rng, RenderOptions(clutter=clutter)).image, c)
            for c in cams]


# The followed windows find the marks the whole tolerance's search finds, at its centres within
# the detector's noise (the measurement starts from another coarse blob: ~0.01 px), with and
# without clutter; never a mark it does not find.
@pytest.mark.parametrize("clutter", [False, True])
@pytest.mark.parametrize("share", [0.5, 0.75, 0.9])
def test_a_followed_part_gives_the_whole_tolerance_result(  # type: ignore[no-untyped-def]
    station1, share: float, clutter: bool
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    frames = _frames(cams, recipe, _displaced(recipe, share), clutter)
    followed = detect_marks_many(frames, recipe, T0, DetectOptions())
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    assert sum(d.found for dets in whole for d in dets) == 8
    for a_dets, b_dets in zip(followed, whole, strict=True):
        for a, b in zip(a_dets, b_dets, strict=True):
            assert a.mark_id == b.mark_id and a.found == b.found
            if b.found:
                assert np.abs(a.uv - b.uv).max() < 0.01


# Without clutter the small windows' coarse blobs give the part's pose: a part displaced up to
# nine tenths of the tolerance (90 mm / 9°) is placed within a few millimetres and tenths of a
# degree, far inside the small windows' reach around it (25 mm / 2.5°).
@pytest.mark.parametrize("share", [0.5, 0.75, 0.9])
def test_the_blobs_of_the_small_windows_give_the_pose(  # type: ignore[no-untyped-def]
    station1, share: float
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    T = _displaced(recipe, share)
    frames = _frames(cams, recipe, T, clutter=False)
    first = [_search(img, cam, recipe, T0, DetectOptions(), 0.25) for img, cam in frames]
    assert any(_unfound(s) for s in first)  # the part is beyond the first reach
    est = pose_from_blobs([(cam, s.live, s.cands) for (_, cam), s in zip(frames, first,
                                                                       strict=True)],
                          recipe, T0)
    assert est is not None
    D = np.linalg.solve(T, est)
    c = np.asarray(recipe.mark_centroid(), dtype=float)
    assert np.linalg.norm(D[:3, :3] @ c + D[:3, 3] - c) < 5.0
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.5


# One camera holds two marks: no pose, and the image goes to the whole tolerance's windows.
def test_too_few_marks_for_a_pose_fall_back_to_the_whole_tolerance(  # type: ignore[no-untyped-def]
    station1,
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    frames = _frames(cams[:1], recipe, _displaced(recipe, 0.5), clutter=False)
    first = _search(frames[0][0], cams[0], recipe, T0, DetectOptions(), 0.25)
    assert _unfound(first)
    assert pose_from_blobs([(cams[0], first.live, first.cands)], recipe, T0) is None
    one = detect_marks_many(frames, recipe, T0, DetectOptions())
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    assert [d.found for d in one[0]] == [d.found for d in whole[0]] == [True, True]
    for a, b in zip(one[0], whole[0], strict=True):
        assert np.abs(a.uv - b.uv).max() < 1e-9  # the very search the whole tolerance makes
