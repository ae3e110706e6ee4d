"""Window mode: find each recipe mark near where the prior pose predicts it, keeping its identity.

A mark's window is its predicted ellipse widened by how far the mark can move when the part is
anywhere within the recipe's tolerances (``max_offset_mm``, ``max_offset_deg``), computed from
the geometry of this camera. The search first uses small windows, quickly searched: for a part
near the prior pose, or near where the last good part was (``near``), within
``DetectOptions.first_reach_mm`` / ``first_reach_deg`` when the tolerances are wider. When a
mark had no blob there that it could be given (within its gate), the blobs the small windows did
hold give the part's pose (follow.py) and every image is searched in the small windows around
that pose (but a mark whose first window held it near there, unclipped, keeps those blobs); an
image where a mark is still not found is searched over the whole tolerance. Accepted candidates
from all windows are assigned to marks jointly (least total distance to the predictions), so two
marks never take the same blob. Marks found off the pose their windows' corrections were taken
at, in a direction the correction feels, are corrected at the pose of their centres (settle.py).
An image's windows and the blobs they hold are layout.py's; measuring and assigning the blobs,
assign.py's.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from functools import partial

import numpy as np

from mvpose_core.detect.assign import Search, gate_px, measure_all
from mvpose_core.detect.follow import AGREE_PX, held_predictions, pose_from_blobs
from mvpose_core.detect.geometry import (
    MarkPrediction,
    predict_marks_cached,
    predict_marks_cached_many,
)
from mvpose_core.detect.layout import (
    FACES_AWAY,
    Box,
    Boxes,
    holds,
    search_windows,
    whole_boxes,
    window_box,
    windows_of,
)
from mvpose_core.detect.settle import SETTLE_PX, needed, offsets_px, settled
from mvpose_core.detect.types import DetectOptions, MarkDetection, check_image
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array


def detect_marks(
    image: np.ndarray,
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf_prior: Array,
    options: DetectOptions = DetectOptions(),  # noqa: B008 - frozen, immutable default
    near: Array | None = None,
) -> list[MarkDetection]:
    """One detection per mark the recipe expects ``cam`` to see: found, or the reason why not
    (``near``: as for :func:`detect_marks_many`)."""
    return detect_marks_many([(image, cam)], recipe, T_rf_from_pf_prior, options, near=near)[0]


def detect_marks_many(
    frames: Sequence[tuple[np.ndarray, ViewCamera]],
    recipe: RecipeConfig,
    T_rf_from_pf_prior: Array,
    options: DetectOptions = DetectOptions(),  # noqa: B008 - frozen, immutable default
    map_fn: Callable[..., Iterable[Search]] = map,
    near: Array | None = None,
) -> list[list[MarkDetection]]:
    """:func:`detect_marks` for the images of several cameras of one part, in their order.

    The candidates of each image are searched by ``map_fn`` (give a thread pool's ``map`` to
    search the images in parallel: the search is OpenCV, which releases the GIL); all candidates
    of all images are then measured in one batch, which costs little more than one image's.
    Each image's result is what :func:`detect_marks` gives for it alone (tested); for a part
    beyond the first reach, the pose of all images' blobs may find an image's marks in small
    windows, the same marks at the same centres within the detector's noise (~0.01 px,
    tested). A bad image raises ``ValueError`` naming its camera.

    Two reaches (``options.first_reach_mm`` / ``first_reach_deg``, when the recipe's tolerances
    are wider): the windows first allow for a part near the prior pose; an image where a mark
    that faces its camera was not found is searched again with windows for the recipe's whole
    tolerance, and that result is the image's. Before that, when a facing mark has no blob in
    its small window that it could be given (:func:`_unfound`), the pose of the blobs that the
    small windows held (three marks or more, :func:`~mvpose_core.detect.follow.pose_from_blobs`)
    moves every image's small windows there (a mark whose blobs already agree with it keeps
    them, :func:`_kept_at`); only an image still missing a blob then gets the whole tolerance's
    windows.
    ``near`` (the pose where the last part was, :func:`~mvpose_core.detect.follow.next_near`)
    puts the first search's small windows there instead of at the prior, held to what the
    whole tolerance's search at the prior accepts; it is ignored for a recipe with one reach.

    When a mark found in the first windows lies more than
    :data:`~mvpose_core.detect.settle.SETTLE_PX` from its prediction, and the correction at
    the marks' pose would move by more than 0.01 px (:func:`~mvpose_core.detect.settle.
    needed`), every found mark is corrected at the pose of the found centres
    (:func:`~mvpose_core.detect.settle.settled`): the same blobs and ellipse centres, the
    correction the one at the estimate within far below 0.01 px.
    """
    checked = [(check_image(img, cam.model, f"camera {cam.key!r}"), cam) for img, cam in frames]
    out: list[list[MarkDetection]] = [[] for _ in checked]
    offsets: dict[int, dict[str, Array]] = {}  # per image: its found marks' offsets (px)
    followed = False  # whether the images were searched around the blobs' pose
    todo = list(range(len(checked)))
    tol = recipe.tolerances
    first = options.first_reach(tol.max_offset_mm, tol.max_offset_deg)
    reaches = (1.0,) if first is None else (first, 1.0)
    start = T_rf_from_pf_prior if near is None or first is None else near
    for n, reach in enumerate(reaches):
        if n == 0 and start is not T_rf_from_pf_prior:
            search = partial(_search_followed, checked, recipe, T_rf_from_pf_prior, start,
                             options, reach, None)
        else:
            search = partial(_search_image, checked, recipe, T_rf_from_pf_prior, options, reach)
        searches = dict(zip(todo, map_fn(search, todo), strict=True))
        if n + 1 < len(reaches):
            # An image with a mark that has no blob it could be given in its small window would
            # be searched again whatever its measurement says. The blobs the small windows did
            # hold give the part's pose (follow.py): every image is searched in the small
            # windows around it. An image with a mark still without a blob is searched with the
            # whole tolerance's windows; only those blobs are measured, in the same batch as the
            # other images'.
            wider = [k for k in todo if _unfound(searches[k], options)]
            if wider:
                wider, followed = _follow(checked, recipe, T_rf_from_pf_prior, start, options,
                                          reach, map_fn, searches)
            if wider:
                search = partial(_search_image, checked, recipe, T_rf_from_pf_prior, options,
                                 reaches[-1])
                searches.update(zip(wider, map_fn(search, wider), strict=True))
        else:
            wider = []
        for k, dets in zip(todo, measure_all([searches[k] for k in todo],
                                          [checked[k][0] for k in todo], recipe, options),
                           strict=True):
            out[k] = dets
            if n == 0 and not followed:  # found around ``start``, with its correction
                offsets[k] = offsets_px(searches[k].live, dets)
        todo = [k for k in todo if k not in wider
                and any(not d.found and d.reason != FACES_AWAY for d in out[k])]
        if not todo:
            break
    far = any(float(np.hypot(*du)) > SETTLE_PX for o in offsets.values() for du in o.values())
    # Only for windows at the prior (whose sensitivities are known; around the last part, the
    # marks lie within millimetres of it).
    if options.correct_perspective and far and start is T_rf_from_pf_prior and needed(
            [(checked[k][1], o) for k, o in offsets.items()], recipe, start):
        # The marks lie away from the pose their corrections were taken at, in a direction
        # the correction feels: corrected at the pose of their centres, the server measures
        # the pose once (settle.py).
        out = settled([(cam, dets) for (_, cam), dets in zip(checked, out, strict=True)],
                      recipe, T_rf_from_pf_prior, start)
    return out


def _follow(
    checked: list[tuple[np.ndarray, ViewCamera]], recipe: RecipeConfig, T_prior: Array,
    start: Array, options: DetectOptions, reach: float,
    map_fn: Callable[..., Iterable[Search]], searches: dict[int, Search],
) -> tuple[list[int], bool]:
    """Search every image in the small windows around the pose of the blobs found so far
    (``searches``, made around ``start``, is updated); the images that still lack a blob for
    a facing mark, to be searched over the whole tolerance (all the unfound ones when there is
    no pose), and whether there was a pose."""
    keys = list(searches)
    T = pose_from_blobs([(checked[k][1], searches[k].live, searches[k].cands) for k in keys],
                        recipe, T_prior, start)
    if T is None:
        return [k for k in keys if _unfound(searches[k], options)], False
    # the windows around the pose are new at every trigger: predicted in every camera at once
    predict_marks_cached_many([checked[k][1] for k in keys], recipe, T, options.size_tolerance,
                              options.shape_slack_deg, reach)
    # A mark whose first window already held it whole, near its projection at the pose, keeps
    # those blobs; only the other marks' windows around the pose are searched (an image whose
    # marks are laid out otherwise there: all of them).
    ats = {k: _at_pose(checked[k], recipe, T_prior, T, options, reach) for k in keys}
    kept: dict[int, tuple[Search, frozenset[str]] | None] = {
        k: _kept_at(searches[k], checked[k], recipe, T_prior, T, options, reach, ats[k])
        for k in keys}
    only = {k: None if v is None else v[1] for k, v in kept.items()}
    again = [k for k in keys if only[k] is None or only[k]]
    search = partial(_search_followed, checked, recipe, T_prior, T, options, reach, only,
                     ats=ats)
    found = dict(zip(again, map_fn(search, again), strict=True))
    for k in keys:
        v = kept[k]
        searches[k] = found[k] if v is None else _joined(v[0], found.get(k))
    return [k for k in keys if _unfound(searches[k], options)], True


def _at_pose(frame: tuple[np.ndarray, ViewCamera], recipe: RecipeConfig, T_prior: Array,
             T: Array, options: DetectOptions, reach: float) -> tuple[list[MarkPrediction],
                                                                     Boxes]:
    """An image's predictions at ``T`` held to the whole tolerance's ranges, and the whole
    tolerance's windows at the prior: what :func:`_kept_at` and :func:`_search_followed` judge
    its blobs by."""
    H, W = frame[0].shape
    return (held_predictions(frame[1], recipe, T_prior, T, options, reach),
            whole_boxes(frame[1], recipe, T_prior, options, W, H))


def _kept_at(
    s: Search, frame: tuple[np.ndarray, ViewCamera], recipe: RecipeConfig, T_prior: Array,
    T: Array, options: DetectOptions, reach: float,
    at: tuple[list[MarkPrediction], Boxes] | None = None,
) -> tuple[Search, frozenset[str]] | None:
    """The first search's blobs as the small windows around ``T`` would judge them, and the
    marks whose windows there are still to be searched; None: search every window.

    A mark keeps its blobs when one is within :data:`AGREE_PX` of its projection at ``T`` and
    none touches its first window's edge (a clipped blob's coarse centre is off and its
    measurement may fail); only those inside both its followed window and the whole
    tolerance's at the prior are kept, judged by the predictions at ``T`` held to the whole
    tolerance's ranges, as :func:`_search_followed`'s. None when the marks with a window in
    the image differ between the first windows and those at ``T`` (``at``: :func:`_at_pose`'s,
    computed when None)."""
    image, cam = frame
    H, W = image.shape
    at_T, whole = _at_pose(frame, recipe, T_prior, T, options, reach) if at is None else at
    inside, boxes, results = windows_of(at_T, options, W, H)
    live = list(inside)
    if (len(live) < sum(p.facing for p in at_T)  # a window outside the image
            or [p.mark.mark_id for p in live] != [p.mark.mark_id for p in s.live]):
        return None
    near = [False] * len(live)
    clipped = [False] * len(live)
    first: dict[int, Box] = {}  # the first windows, as needed
    for k, c in s.cands:
        b = first.get(k)
        if b is None:
            b = first[k] = window_box(s.live[k], options, W, H)
        (u, v), r = c.ellipse.centre, c.ellipse.a + 2.0 * max(s.scales) + 2.0
        if not (b[0] < u - r and u + r < b[2] - 1 and b[1] < v - r and v + r < b[3] - 1):
            clipped[k] = True
        if math.hypot(u - live[k].uv[0], v - live[k].uv[1]) <= AGREE_PX:
            near[k] = True
    keep = [n and not c for n, c in zip(near, clipped, strict=True)]
    cands, scales = [], []
    for (k, c), sc in zip(s.cands, s.scales, strict=True):
        u, v = c.ellipse.centre
        if keep[k] and holds(boxes[k], u, v) and holds(whole[live[k].mark.mark_id], u, v):
            cands.append((k, c))
            scales.append(sc)
    preds = predict_marks_cached(cam, recipe, T, options.size_tolerance,
                                 options.shape_slack_deg, reach)
    rest = frozenset(p.mark.mark_id for p, k in zip(live, keep, strict=True) if not k)
    return Search(list(preds), results, live, cands, scales), rest


def _joined(kept: Search, found: Search | None) -> Search:
    """The kept blobs with those found in the other marks' windows (None: no other), less a
    blob found again (within half its radius of a kept one)."""
    if found is None:
        return kept
    assert [p.mark.mark_id for p in found.live] == [p.mark.mark_id for p in kept.live]
    cands, scales = list(kept.cands), list(kept.scales)
    for (k, c), sc in zip(found.cands, found.scales, strict=True):
        if all(np.hypot(*(c.ellipse.centre - d.ellipse.centre)) > 0.5 * c.ellipse.radius
               for _, d in kept.cands):
            cands.append((k, c))
            scales.append(sc)
    return replace(found, cands=cands, scales=scales)


def _search_followed(
    checked: list[tuple[np.ndarray, ViewCamera]], recipe: RecipeConfig, T_prior: Array,
    T: Array, options: DetectOptions, reach: float,
    only: dict[int, frozenset[str] | None] | None, k: int, *,
    ats: dict[int, tuple[list[MarkPrediction], Boxes]] | None = None,
) -> Search:
    """The small windows around the pose ``T`` (those of the marks ``only[k]``; None: all),
    held to what the whole tolerance's search at the prior accepts: only blobs inside the
    mark's whole window, sizes and shapes within its ranges. The perspective correction is the
    one at ``T``, nearer the part than the prior's (the server then seldom measures the pose a
    second time, docs/detection.md; ``ats``: :func:`_at_pose`'s per image, computed when
    None)."""
    image, cam = checked[k]
    s = search_windows(image, cam, recipe, T, options, reach, None if only is None else only[k])
    at_T, whole = (_at_pose(checked[k], recipe, T_prior, T, options, reach) if ats is None
                   else ats[k])
    held = {p.mark.mark_id: p for p in at_T}
    live = [held[p.mark.mark_id] for p in s.live]
    kept = [(j, (k_, c)) for j, (k_, c) in enumerate(s.cands)
            if holds(whole[live[k_].mark.mark_id], *c.ellipse.centre)]
    return replace(s, live=live, cands=[kc for _, kc in kept],
                   scales=[s.scales[j] for j, _ in kept])


def _unfound(s: Search, options: DetectOptions) -> bool:
    """Whether a mark that faces the camera has no blob it could be given (or no window in the
    image): it cannot be found in this search.

    A blob can be given to a mark only within the mark's gate (its possible shift and
    ``window_extra_px`` from its prediction, :func:`~mvpose_core.detect.assign.assign`); a
    window is wider than that by the mark's largest radius, so a blob of a part beyond the
    window's reach may lie in it and still never be the mark's. Such a blob counts from a
    little beyond the gate (its coarse centre is within a few coarse pixels of the measured
    one)."""
    if len(s.live) < sum(p.facing for p in s.preds):
        return True
    held = set()
    for _, c in s.cands:
        u, v = c.ellipse.centre
        for j, p in enumerate(s.live):
            if math.hypot(u - p.uv[0], v - p.uv[1]) <= gate_px(p, options) + _COARSE_SLACK_PX:
                held.add(j)
    return len(held) < len(s.live)


#: how far beyond a mark's gate (px) a coarse blob still counts as one the mark could be given
_COARSE_SLACK_PX = 8.0


def _search_image(
    checked: list[tuple[np.ndarray, ViewCamera]], recipe: RecipeConfig, T_prior: Array,
    options: DetectOptions, reach: float, k: int,
) -> Search:
    return search_windows(checked[k][0], checked[k][1], recipe, T_prior, options, reach)
