"""An image's windows are remembered per prediction list (mvpose_core/detect/layout.py): a
search from remembered windows is the one made from scratch, and what one search's caller does
with its results never reaches the next search."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvpose_core.detect import DetectOptions
from mvpose_core.detect.geometry import predict_marks_cached
from mvpose_core.detect.layout import merge_windows, search_windows, whole_boxes, window_box
from mvpose_core.detect.types import MarkDetection
from mvpose_core.render import render_view
from mvpose_core.scene import sighted_marks, view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import displaced

STATION1 = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "station1.yaml"


def test_remembered_windows_search_as_new_and_each_search_owns_its_results() -> None:
    station = load_station(STATION1)
    recipe = station.recipe()
    cam = next(vc for vc in view_cameras(station)
               if sighted_marks(recipe, vc.view, vc.camera_id))
    T0 = recipe.T_rf_from_pf0.matrix
    image = render_view(cam, recipe, displaced(recipe, 0.1), np.random.default_rng(3)).image
    opts = DetectOptions()
    H, W = image.shape
    first = search_windows(image, cam, recipe, T0, opts, 0.25)
    assert first.live and first.cands
    # the windows are those of the predictions, and their groups those merge_windows makes
    preds = predict_marks_cached(cam, recipe, T0, opts.size_tolerance, opts.shape_slack_deg,
                                 0.25)
    boxes = [window_box(p, opts, W, H) for p in preds if p.facing]
    assert [p.mark.mark_id for p in first.live] == [p.mark.mark_id for p in preds if p.facing]
    assert len(merge_windows(boxes, [p.dark for p in first.live])) >= 1
    # a caller that fills in its search's results (as assign does) leaves the next one's alone
    for mid in list(first.results):
        first.results[mid] = MarkDetection.missing(mid, "changed by the caller")
    first.live.clear()
    again = search_windows(image, cam, recipe, T0, opts, 0.25)
    assert {d.reason for d in again.results.values()} == {"nothing mark-like in window"}
    assert [p.mark.mark_id for p in again.live] == [p.mark.mark_id for p in preds if p.facing]
    assert len(again.cands) == len(first.cands)
    for (k, a), (j, b) in zip(again.cands, first.cands, strict=True):
        assert k == j and np.array_equal(a.ellipse.centre, b.ellipse.centre)
    # only some marks' windows: a subset of the blobs, each still given to its own mark
    only = frozenset({again.live[0].mark.mark_id})
    some = search_windows(image, cam, recipe, T0, opts, 0.25, only)
    assert some.cands and {k for k, _ in some.cands} == {0}
    # the whole tolerance's windows at the prior, one per mark, each holding its small one
    whole = whole_boxes(cam, recipe, T0, opts, W, H)
    assert set(whole) == {p.mark.mark_id for p in preds}
    for p, b in zip([p for p in preds if p.facing], boxes, strict=True):
        w = whole[p.mark.mark_id]
        assert w[0] <= b[0] and w[1] <= b[1] and b[2] <= w[2] and b[3] <= w[3]
