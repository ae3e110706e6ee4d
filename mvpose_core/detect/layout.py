"""An image's windows and the blobs found in them, before measurement.

A mark's window is its predicted position widened by its possible shift, its largest radius and
``window_extra_px`` (:func:`window_box`); windows of one polarity that overlap by half or more
are searched once, as their union (:func:`merge_windows`), at the coarsest reduction that keeps
the smallest accepted mark 2.5 px wide (:func:`coarse_scale`). :func:`search_windows` gives an
image's :class:`~mvpose_core.detect.assign.Search`: its predictions, which marks have a window
in the image, and each blob with the mark whose window holds it.

What depends only on the predictions and the image size (the windows, their groups, the marks
without a window and their reasons) is remembered per prediction list
(:data:`_LAYOUTS`): the predictions at the prior, or around the last part, are the same objects
trigger after trigger, so a trigger's search is the OpenCV work and the blobs' bookkeeping only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.detect.assign import Search
from mvpose_core.detect.candidates import Candidate, find_candidates
from mvpose_core.detect.geometry import MarkPrediction, predict_marks_cached
from mvpose_core.detect.types import DetectOptions, MarkDetection
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

FACES_AWAY = "mark faces away from the camera"

Box = tuple[int, int, int, int]
Boxes = dict[str, Box]


@dataclass(frozen=True)
class _Group:
    """Windows searched together: their marks (indices into the live predictions), the union
    of their boxes, their polarity, radius range and reduction."""

    members: tuple[int, ...]
    region: Box
    dark: bool
    radius_range: tuple[float, float]
    scale: int


@dataclass(frozen=True)
class _Layout:
    """An image's windows for one prediction list: what :func:`search_windows` needs before
    it looks at a pixel."""

    results: dict[str, MarkDetection]  # per mark, the reason it is not found until it is
    live: tuple[MarkPrediction, ...]  # the predictions whose window lies in the image
    boxes: tuple[Box, ...]  # their windows
    # the groups to search, per set of marks searched (None: all); filled as asked for
    groups: dict[frozenset[str] | None, tuple[_Group, ...]] = field(default_factory=dict)

    def groups_of(self, only: frozenset[str] | None) -> tuple[_Group, ...]:
        got = self.groups.get(only)
        if got is None:
            live, boxes = self.live, self.boxes
            idx = [k for k, p in enumerate(live) if only is None or p.mark.mark_id in only]
            made = []
            for group, region in merge_windows([boxes[k] for k in idx],
                                               [live[k].dark for k in idx]):
                members = tuple(idx[m] for m in group)
                lo = min(live[k].radius_range[0] for k in members)
                hi = max(live[k].radius_range[1] for k in members)
                made.append(_Group(members, region, live[members[0]].dark, (lo, hi),
                                   coarse_scale(lo)))
            got = self.groups[only] = tuple(made)  # the same value from any thread
        return got


#: the layouts of recent prediction lists (held by the prediction caches, so the same objects)
_LAYOUTS: IdentityCache[_Layout] = IdentityCache(64)
_WHOLE: IdentityCache[Boxes] = IdentityCache(32)


def _layout(preds: list[MarkPrediction], options: DetectOptions, W: int, H: int) -> _Layout:
    def make() -> _Layout:
        results: dict[str, MarkDetection] = {}
        live: list[MarkPrediction] = []
        boxes: list[Box] = []
        for p in preds:
            mid = p.mark.mark_id
            if not p.facing:
                results[mid] = MarkDetection.missing(mid, FACES_AWAY)
                continue
            box = window_box(p, options, W, H)
            if box[2] - box[0] < 8 or box[3] - box[1] < 8:
                results[mid] = MarkDetection.missing(mid, "outside image")
                continue
            results[mid] = MarkDetection.missing(mid, "nothing mark-like in window")
            live.append(p)
            boxes.append(box)
        return _Layout(results, tuple(live), tuple(boxes))

    return _LAYOUTS.get((preds,), (options.window_extra_px, W, H), make)


def windows_of(preds: list[MarkPrediction], options: DetectOptions, W: int, H: int,
               ) -> tuple[tuple[MarkPrediction, ...], tuple[Box, ...], dict[str, MarkDetection]]:
    """The predictions whose window lies in the image, their windows, and every mark's
    reason while it is not found (a new dict), remembered per prediction list."""
    lay = _layout(preds, options, W, H)
    return lay.live, lay.boxes, dict(lay.results)


def search_windows(
    image: np.ndarray,
    cam: ViewCamera,
    recipe: RecipeConfig,
    T_rf_from_pf_prior: Array,
    options: DetectOptions,
    reach: float = 1.0,
    only: frozenset[str] | None = None,
) -> Search:
    """One image's windows (those of the marks ``only``; None: all) and their blobs."""
    preds = predict_marks_cached(
        cam, recipe, T_rf_from_pf_prior, options.size_tolerance, options.shape_slack_deg, reach
    )
    H, W = image.shape
    lay = _layout(preds, options, W, H)
    live, boxes = lay.live, lay.boxes
    cands: list[tuple[int, Candidate]] = []
    scales: list[int] = []
    for g in lay.groups_of(only):
        # Large tolerances make the windows of one camera's marks overlap almost entirely:
        # search their union once instead of the same pixels once per mark.
        found = find_candidates(image, g.region, g.dark, g.radius_range, options.min_contrast,
                                g.scale, options.max_candidates * len(g.members))
        one = g.members[0] if len(g.members) == 1 else None
        for c in found:
            cu, cv = float(c.ellipse.centre[0]), float(c.ellipse.centre[1])
            # The blob belongs to the nearest mark whose own window holds it.
            if one is not None:
                if holds(boxes[one], cu, cv):
                    cands.append((one, c))
                    scales.append(g.scale)
                continue
            inside = [k for k in g.members if holds(boxes[k], cu, cv)]
            if inside:
                k = min(inside, key=lambda j: math.hypot(cu - live[j].uv[0], cv - live[j].uv[1]))
                cands.append((k, c))
                scales.append(g.scale)
    return Search(list(preds), dict(lay.results), list(live), cands, scales)


def whole_boxes(cam: ViewCamera, recipe: RecipeConfig, T_prior: Array, options: DetectOptions,
                W: int, H: int) -> Boxes:
    """Every mark's window for the whole tolerance at the prior (remembered; not to be
    changed)."""
    preds = predict_marks_cached(cam, recipe, T_prior, options.size_tolerance,
                                 options.shape_slack_deg, 1.0)
    return _WHOLE.get((preds,), (options.window_extra_px, W, H),
                      lambda: {p.mark.mark_id: window_box(p, options, W, H) for p in preds})


def window_box(p: MarkPrediction, options: DetectOptions, W: int, H: int) -> Box:
    """A mark's window: its predicted position widened by its possible shift, its largest
    radius and the margin, within the image."""
    half = p.max_shift_px + p.radius_range[1] + options.window_extra_px
    pu, pv = float(p.uv[0]), float(p.uv[1])
    u0, v0 = math.floor(pu - half), math.floor(pv - half)
    u1, v1 = math.ceil(pu + half) + 1, math.ceil(pv + half) + 1
    return (max(u0, 0), max(v0, 0), min(u1, W), min(v1, H))


def holds(box: Box, u: float, v: float) -> bool:
    return box[0] <= u < box[2] and box[1] <= v < box[3]


def merge_windows(
    boxes: list[tuple[int, int, int, int]], dark: list[bool] | None = None,
    min_overlap: float = 0.5,
) -> list[tuple[list[int], tuple[int, int, int, int]]]:
    """Groups of windows to search together, each with the bounding box of its members.

    Two windows join a group when their marks have the same polarity (``dark``) and their
    intersection covers at least ``min_overlap`` of the smaller one, so merging never searches
    much more area than the windows themselves.
    """
    groups: list[tuple[list[int], tuple[int, int, int, int]]] = []
    for k, b in enumerate(boxes):
        area_b = (b[2] - b[0]) * (b[3] - b[1])
        for members, g in groups:
            if dark is not None and dark[members[0]] != dark[k]:
                continue
            iw = min(b[2], g[2]) - max(b[0], g[0])
            ih = min(b[3], g[3]) - max(b[1], g[1])
            area_g = (g[2] - g[0]) * (g[3] - g[1])
            if iw > 0 and ih > 0 and iw * ih >= min_overlap * min(area_b, area_g):
                members.append(k)
                groups[groups.index((members, g))] = (
                    members,
                    (min(b[0], g[0]), min(b[1], g[1]), max(b[2], g[2]), max(b[3], g[3])),
                )
                break
        else:
            groups.append(([k], b))
    return groups


def coarse_scale(min_radius_px: float) -> int:
    """Largest reduction (1, 2, 4, 8) at which the smallest accepted mark keeps a 2.5 px radius."""
    scale = 1
    while scale < 8 and min_radius_px / (2 * scale) >= 2.5:
        scale *= 2
    return scale

