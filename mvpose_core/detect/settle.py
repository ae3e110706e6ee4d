"""The perspective correction of a moved part's marks at the pose of their measured centres.

A found mark carries the correction at the pose its window was predicted at (the prior, the
last part's, or the pose of a displaced part's blobs). The server measures the pose, computes
the correction at the estimate and, when any moved by more than ``recorrect_px`` (0.01 px),
measures the pose a second time (docs/detection.md). For a part that lies away from that pose
(its marks away from their predictions), that second measurement is avoided here: the pose of
the measured centres (the blobs' refinement, :func:`~mvpose_core.detect.follow.
pose_from_observations`, a few hundred µs against a measurement's millisecond) gives the
correction, which then agrees with the one at the estimate far below 0.01 px.

Only the correction (``uv`` and ``correction``) changes, never which blob a mark has nor its
ellipse centre (``uv_ellipse``). When the centres give no pose, the detections stay as they
were: the server's second measurement still follows.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvpose_core.detect.correction import corrected, corrections_at
from mvpose_core.detect.follow import pose_from_observations
from mvpose_core.detect.geometry import MarkPrediction
from mvpose_core.detect.types import MarkDetection
from mvpose_core.problem import Observation
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array

#: the marks are corrected at their own pose when one lies farther than this (px) from its
#: prediction. The correction moves far less than the marks: by at most 0.9 % of the farthest
#: mark's shift on deploy/stations/station1.yaml (median 0.3 %), 0.2 % on the lab and station2
#: (random poses within a third of the tolerance). At 4 px, two thirds of station1's parts would
#: be measured twice (none of the others'), and the pose and the correction here cost about
#: half a measurement (~0.6 ms): below it, the server's second measurement is left to decide.
SETTLE_PX = 4.0


def moved_px(live: Sequence[MarkPrediction], dets: Sequence[MarkDetection]) -> float:
    """How far (px) the found mark farthest from its prediction lies from it (none found: 0):
    ``live`` the predictions the detections were judged and corrected by."""
    at = {p.mark.mark_id: p.uv for p in live}
    far = 0.0
    for d in dets:
        uv = at.get(d.mark_id)
        if d.found and d.uv is not None and uv is not None:
            far = max(far, float(np.hypot(*(d.uv - uv))))
    return far


def settled(
    groups: Sequence[tuple[ViewCamera, list[MarkDetection]]], recipe: RecipeConfig,
    T_prior: Array, start: Array,
) -> list[list[MarkDetection]]:
    """Each camera's detections corrected at the pose of all their found centres (refined from
    ``start``, within the recipe's tolerance of ``T_prior``); as given when they fix none."""
    obs = [Observation(cam.view, cam.camera_id, d.mark_id, d.uv)
           for cam, dets in groups for d in dets if d.found and d.uv is not None]
    cams = [cam for cam, dets in groups if any(d.found for d in dets)]
    T = pose_from_observations(obs, cams, recipe, T_prior, start)
    if T is None:
        return [dets for _, dets in groups]
    return corrected(groups, corrections_at(groups, recipe, T)[0])
