"""A displaced part's windows predicted from the pose of the blobs its small windows held."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mvpose_core.detect import DetectOptions, detect_marks_many, recorrect
from mvpose_core.detect.follow import _within, next_near, pose_from_blobs
from mvpose_core.detect.layout import search_windows, window_box
from mvpose_core.detect.window import _kept_at, _unfound
from mvpose_core.render import RenderOptions, render_view
from mvpose_core.scene import view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import displaced

STATION1 = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"


@pytest.fixture(scope="module")
def station1():  # type: ignore[no-untyped-def]
    station = load_station(STATION1)
    return view_cameras(station), station.recipe()


def _frames(cams, recipe, T, clutter: bool):  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(7)
    return [(render_view(c, recipe, T, rng, RenderOptions(clutter=clutter)).image, c)
            for c in cams]


def _same_as_whole(cams, recipe, T, followed, whole, once=True) -> None:  # type: ignore[no-untyped-def]
    """The same marks found, at the same ellipse centres within the detector's noise (the
    measurement starts from another coarse blob: ~0.01 px), and the same centres once both are
    corrected at the part's pose; with ``once``, the followed corrections are already within
    the server's recorrect_px (0.01 px) of those at the part's pose (it measures the pose once;
    an image that went to the whole tolerance's windows has the prior's)."""
    assert sum(d.found for dets in whole for d in dets) == 8
    for a_dets, b_dets in zip(followed, whole, strict=True):
        for a, b in zip(a_dets, b_dets, strict=True):
            assert a.mark_id == b.mark_id and a.found == b.found
            if b.found:
                assert np.abs(a.uv_ellipse - b.uv_ellipse).max() < 0.01
    a_at, moved = recorrect(list(zip(cams, followed, strict=True)), recipe, T)
    b_at, _ = recorrect(list(zip(cams, whole, strict=True)), recipe, T)
    assert moved <= 0.01 or not once
    for a_dets, b_dets in zip(a_at, b_at, strict=True):
        for a, b in zip(a_dets, b_dets, strict=True):
            if b.found:
                assert np.abs(a.uv - b.uv).max() < 0.01


# The followed windows find the marks the whole tolerance's search finds, at its centres within
# the detector's noise, with and without clutter; never a mark it does not find.
@pytest.mark.parametrize("clutter", [False, True])
@pytest.mark.parametrize("share", [0.5, 0.75, 0.9])
def test_a_followed_part_gives_the_whole_tolerance_result(  # type: ignore[no-untyped-def]
    station1, share: float, clutter: bool
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    T = displaced(recipe, share)
    frames = _frames(cams, recipe, T, clutter)
    followed = detect_marks_many(frames, recipe, T0, DetectOptions())
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    _same_as_whole(cams, recipe, T, followed, whole)


# The first windows around where the last part was: a part that sits near it (a few mm from it)
# gives the whole tolerance's result from one small-window search; a part that does not (the
# last part at the opposite side of the tolerance, or at the reference) is still found, by the
# pose of the blobs or the whole tolerance's windows.
@pytest.mark.parametrize("clutter", [False, True])
@pytest.mark.parametrize(("share", "last"), [(0.9, 0.88), (0.5, -0.5), (0.0, 0.9), (0.9, 0.0)])
def test_windows_near_the_last_part_give_the_whole_tolerance_result(  # type: ignore[no-untyped-def]
    station1, share: float, last: float, clutter: bool
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    T = displaced(recipe, share)
    frames = _frames(cams, recipe, T, clutter)
    near = displaced(recipe, last)
    followed = detect_marks_many(frames, recipe, T0, DetectOptions(), near=near)
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    _same_as_whole(cams, recipe, T, followed, whole, once=abs(share - last) < 0.1)
    if abs(share - last) < 0.1:  # the part within the first windows around the last one
        first = [search_windows(img, cam, recipe, near, DetectOptions(), 0.25)
                 for img, cam in frames]
        assert not any(_unfound(s, DetectOptions()) for s in first)


# The next trigger's first windows go where the last part was once two parts in a row lay within
# the first reach (25 mm / 2.5°) of each other; that place is remembered anew only when a part
# moved by more than a fifth of the first reach (5 mm / 0.5°) from it, and forgotten near the
# reference. A part that jumped sends the next search back to the reference.
def test_the_next_windows_follow_a_part_that_stays_in_steps(station1) -> None:  # type: ignore[no-untyped-def]
    _, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    opts = DetectOptions()

    def d(share: float) -> np.ndarray:
        return displaced(recipe, share)

    assert next_near(None, None, d(0.5), T0, recipe, opts) is None  # the first part there
    a = next_near(None, d(0.5), d(0.52), T0, recipe, opts)  # the second, 2 mm / 0.2° from it
    assert a is not None and np.allclose(a, d(0.52))
    assert next_near(a, d(0.52), d(0.5), T0, recipe, opts) is a
    b = next_near(a, d(0.5), d(0.6), T0, recipe, opts)  # 10 mm / 1° from the remembered place
    assert b is not a and b is not None and np.allclose(b, d(0.6))
    assert next_near(b, d(0.6), d(0.03), T0, recipe, opts) is None  # back at the reference
    assert next_near(None, None, d(0.03), T0, recipe, opts) is None
    assert next_near(a, d(0.52), d(-0.5), T0, recipe, opts) is None  # a jump: 100 mm / 10°
    assert next_near(a, d(0.52), d(0.5), T0, recipe,
                     DetectOptions(first_reach_mm=None)) is None  # one reach: no windows to move


# "Within mm / deg of a pose" is the marks' centroid moved by at most mm and a rotation of at most
# deg between the two poses, whichever of them it is seen from: the closed form on floats agrees
# with the relative pose T_ref⁻¹ T taken by a linear solve, on parts spread over twice the
# tolerance around poses away from the reference.
def test_the_tolerance_check_is_the_parts_move_between_the_poses(station1) -> None:  # type: ignore[no-untyped-def]
    _, recipe = station1
    rng = np.random.default_rng(11)
    c = np.array(recipe.mark_centroid(), dtype=float)
    agree, outcomes = 0, set()
    for _ in range(300):
        T_ref = displaced(recipe, rng.uniform(0, 1), rng.normal(size=3), rng.normal(size=3))
        T = displaced(recipe, rng.uniform(0, 2), rng.normal(size=3), rng.normal(size=3))
        mm, deg = rng.uniform(5, 100), rng.uniform(0.5, 10)
        D = np.linalg.solve(T_ref, T)
        moved = np.linalg.norm(D[:3, :3] @ c + D[:3, 3] - c)
        angle = np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
        if min(abs(moved - mm), abs(angle - deg)) < 1e-6:
            continue  # on the boundary, rounding decides
        inside = bool(moved <= mm and angle <= deg)
        assert _within(T, T_ref, recipe, mm, deg) == inside
        agree += 1
        outcomes.add(inside)
    assert agree > 290 and outcomes == {True, False}


# Without clutter the small windows' coarse blobs give the part's pose: a part displaced up to
# nine tenths of the tolerance (90 mm / 9°) is placed within a few millimetres and tenths of a
# degree, far inside the small windows' reach around it (25 mm / 2.5°).
@pytest.mark.parametrize("share", [0.5, 0.75, 0.9])
def test_the_blobs_of_the_small_windows_give_the_pose(  # type: ignore[no-untyped-def]
    station1, share: float
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    T = displaced(recipe, share)
    frames = _frames(cams, recipe, T, clutter=False)
    first = [search_windows(img, cam, recipe, T0, DetectOptions(), 0.25) for img, cam in frames]
    assert any(_unfound(s, DetectOptions()) for s in first)  # the part is beyond the first reach
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
    frames = _frames(cams[:1], recipe, displaced(recipe, 0.5), clutter=False)
    first = search_windows(frames[0][0], cams[0], recipe, T0, DetectOptions(), 0.25)
    assert _unfound(first, DetectOptions())
    assert pose_from_blobs([(cams[0], first.live, first.cands)], recipe, T0) is None
    one = detect_marks_many(frames, recipe, T0, DetectOptions())
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    assert [d.found for d in one[0]] == [d.found for d in whole[0]] == [True, True]
    for a, b in zip(one[0], whole[0], strict=True):
        assert np.abs(a.uv - b.uv).max() < 1e-9  # the very search the whole tolerance makes


# A first part there: a mark whose first window already held it whole, near its projection at
# the blobs' pose, keeps its blobs (judged by the pose's predictions); only the other marks'
# windows are searched again, and a blob that touches its first window's edge is searched again.
def test_marks_whose_first_windows_held_them_keep_their_blobs(  # type: ignore[no-untyped-def]
    station1,
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    opts = DetectOptions()
    frames = _frames(cams, recipe, displaced(recipe, 0.5), clutter=False)
    first = [search_windows(img, cam, recipe, T0, opts, 0.25) for img, cam in frames]
    T = pose_from_blobs([(cam, s.live, s.cands) for (_, cam), s in zip(frames, first,
                                                                     strict=True)], recipe, T0)
    assert T is not None
    kept = [_kept_at(s, f, recipe, T0, T, opts, 0.25) for s, f in zip(first, frames,
                                                                      strict=True)]
    assert all(k is not None for k in kept)
    # the first camera's first windows missed T1 and clipped T2 at their edge; the others held
    # their marks whole
    assert [k[1] for k in kept if k is not None] == [{"T1", "T2"}] + [frozenset()] * 3
    assert kept[0] is not None and kept[0][0].cands == []
    for k, s in zip(kept[1:], first[1:], strict=True):
        assert k is not None and [c for _, c in k[0].cands] == [c for _, c in s.cands]
        assert all(np.hypot(*(c.ellipse.centre - k[0].live[j].uv)) < 12.0
                   for j, c in k[0].cands)
    # The same blob, as large as to reach its first window's edge (clipped there): its mark is
    # searched again, though its centre is where it was.
    s = first[1]
    j, c = s.cands[0]
    u0 = window_box(s.live[j], opts, *frames[1][0].shape[::-1])[0]
    edge = replace(c, ellipse=replace(c.ellipse, a=float(c.ellipse.centre[0]) - u0))
    clipped = _kept_at(replace(s, cands=[(j, edge)] + s.cands[1:]), frames[1], recipe, T0, T,
                       opts, 0.25)
    assert clipped is not None and clipped[1] == {s.live[j].mark.mark_id}
    assert [c for _, c in clipped[0].cands] == [c for _, c in s.cands[1:]]


# A part whose every first window holds a blob, most of them too far from their marks'
# predictions to be given to them (beyond the gate: a window is wider by the largest radius):
# those marks cannot be found there, so the blobs' pose moves the windows (the corrections are
# then at that pose, within recorrect_px of the part's: measured once), instead of the whole
# tolerance's windows at the prior after measuring.
@pytest.mark.parametrize("clutter", [False, True])
def test_blobs_beyond_their_gates_send_the_search_to_the_blobs_pose(  # type: ignore[no-untyped-def]
    station1, clutter: bool
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    opts = DetectOptions()
    T = displaced(recipe, 0.43, np.array([0.41, 0.36, 0.84]), np.array([-0.37, 0.01, -0.93]))
    frames = _frames(cams, recipe, T, clutter)
    first = [search_windows(img, cam, recipe, T0, opts, 0.25) for img, cam in frames]
    assert all({k for k, _ in s.cands} == set(range(len(s.live))) for s in first)
    assert sum(_unfound(s, opts) for s in first) >= 2
    gate = [[p.max_shift_px + opts.window_extra_px for p in s.live] for s in first]
    assert any(np.hypot(*(c.ellipse.centre - s.live[k].uv)) > g[k] + 8.0
               for s, g in zip(first, gate, strict=True) for k, c in s.cands)
    followed = detect_marks_many(frames, recipe, T0, opts)
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    _same_as_whole(cams, recipe, T, followed, whole, once=True)


# A part within the first reach but away from the reference (the station bench's place 0): all
# its marks are found in the first windows, which carry the correction at the reference (the
# server would measure the pose twice). They are corrected at the pose of their centres instead,
# so the server measures it once: the same ellipse centres as the whole tolerance's search, and
# corrections within recorrect_px of those at the part's pose.
@pytest.mark.parametrize("clutter", [False, True])
def test_marks_away_from_their_first_windows_pose_are_corrected_at_their_own(  # type: ignore[no-untyped-def]
    station1, clutter: bool
) -> None:
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    rng = np.random.default_rng(28)  # bench/moving_part.py's first place (0.31 of the tolerance)
    T = displaced(recipe, float(rng.uniform(0.0, 0.9)), rng.normal(size=3), rng.normal(size=3))
    frames = _frames(cams, recipe, T, clutter)
    first = detect_marks_many(frames, recipe, T0, DetectOptions())
    whole = detect_marks_many(frames, recipe, T0, DetectOptions(first_reach_mm=None))
    _, at_prior = recorrect(list(zip(cams, first, strict=True)), recipe, T0)
    assert at_prior > 0.01  # the reference's corrections: the server would measure twice
    _same_as_whole(cams, recipe, T, first, whole)


# A part at the reference keeps the reference's corrections (no pose is computed for it).
def test_marks_at_their_predictions_keep_the_first_windows_corrections(station1) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    found = detect_marks_many(_frames(cams, recipe, T0, False), recipe, T0, DetectOptions())
    assert sum(d.found for dets in found for d in dets) == 8
    _, moved = recorrect(list(zip(cams, found, strict=True)), recipe, T0)
    assert moved < 1e-9  # the reference's own (at a pose of the centres: ~1e-4 px from them)


# A part off the reference in a direction the correction hardly feels (0.2 of the tolerance
# along the default direction: it moves by 0.006 px): its marks keep the first windows'
# correction, already within recorrect_px of the one at its pose (no pose computed for it).
def test_marks_off_in_a_direction_the_correction_hardly_feels_keep_theirs(station1) -> None:  # type: ignore[no-untyped-def]
    cams, recipe = station1
    T0 = recipe.T_rf_from_pf0.matrix
    T = displaced(recipe, 0.2)
    found = detect_marks_many(_frames(cams, recipe, T, False), recipe, T0, DetectOptions())
    assert sum(d.found for dets in found for d in dets) == 8
    _, at_prior = recorrect(list(zip(cams, found, strict=True)), recipe, T0)
    assert at_prior < 1e-9
    _, at_pose = recorrect(list(zip(cams, found, strict=True)), recipe, T)
    assert 0.001 < at_pose <= 0.01
