"""The perspective correction of a moved part's marks at the pose of their measured centres.

A found mark carries the correction at the pose its window was predicted at (the prior, the
last part's, or the pose of a displaced part's blobs). The server measures the pose, computes
the correction at the estimate and, when any moved by more than ``recorrect_px`` (0.01 px),
measures the pose a second time (~1 ms; docs/detection.md). For marks found in their first
windows away from their predictions, that second measurement is avoided here when it would
come: :func:`needed` tells from the marks' offsets (a first-order model of how the marks'
images and corrections move with the pose, a few tens of µs) whether the correction at their
pose moves by more than 0.01 px; then :func:`settled` corrects every found mark at the pose of
the measured centres (the blobs' refinement, :func:`~mvpose_core.detect.follow.
pose_from_observations`, and the correction there: ~0.6 ms), which agrees with the one at the
estimate far below 0.01 px.

Only the correction (``uv`` and ``correction``) changes, never which blob a mark has nor its
ellipse centre (``uv_ellipse``). When the centres give no pose, the detections stay as they
were: the server's second measurement still follows.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mvpose_core.cache import IdentityCache
from mvpose_core.detect.correction import corrected, corrections_at, perspective_corrections
from mvpose_core.detect.follow import pose_from_observations
from mvpose_core.detect.geometry import MarkPrediction
from mvpose_core.detect.types import MarkDetection
from mvpose_core.problem import Observation
from mvpose_core.scene import ViewCamera
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, rotvec_to_matrix

#: the marks are looked at only when one lies farther than this (px) from its prediction: below
#: it the correction moves by at most ~0.01 px on every station we have (0.9 % of the farthest
#: mark's shift on deploy/stations/station1.yaml, 0.2 % on the lab and station2)
SETTLE_PX = 1.0
#: and corrected at their own pose only when the correction there is predicted to move by more
#: than this (px): the server's recorrect_px, beyond which it measures twice
SETTLE_CORR_PX = 0.01
#: the finite steps of the sensitivity: 1 mm along the part's axes, 0.1° about them (at the
#: marks' centroid)
_STEP_MM, _STEP_RAD = 1.0, np.deg2rad(0.1)


def offsets_px(live: Sequence[MarkPrediction], dets: Sequence[MarkDetection]) -> dict[str, Array]:
    """Each found mark's offset (px) from its prediction in ``live``, the predictions the
    detections were judged and corrected by."""
    at = {p.mark.mark_id: p.uv for p in live}
    return {d.mark_id: d.uv - at[d.mark_id] for d in dets
            if d.found and d.uv is not None and d.mark_id in at}


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


def needed(
    offsets: Sequence[tuple[ViewCamera, dict[str, Array]]], recipe: RecipeConfig, T: Array,
) -> bool:
    """Whether the correction at the pose of the marks found moves by more than
    :data:`SETTLE_CORR_PX` from the one at ``T`` their windows carry: per camera, each found
    mark's offset from its prediction at ``T`` (px). To first order: the pose step that
    explains the offsets best (least squares through the marks' image shifts per step of the
    pose, :func:`_sensitivity`) moves each correction by its own sensitivity times that step.
    A few tens of µs (the sensitivity is computed once per camera and pose), against the
    ~0.6 ms of :func:`settled` and the ~1 ms of the server's second measurement; a part that
    moved mostly in a direction the correction does not feel is measured once without it."""
    B: list[Array] = []
    A: list[Array] = []
    d: list[Array] = []
    for cam, off in offsets:
        sens = _sensitivity(cam, recipe, T)
        for mid, du in off.items():
            if mid in sens:
                B.append(sens[mid][0])
                A.append(sens[mid][1])
                d.append(du)
    if len(d) < 3:
        return True  # too few marks to tell: as without the gate
    step = np.linalg.lstsq(np.concatenate(B), np.concatenate(d), rcond=None)[0]
    moved = np.stack(A) @ step
    return bool(np.sqrt(np.einsum("ni,ni->n", moved, moved).max()) > SETTLE_CORR_PX)


_SENSITIVITY: IdentityCache[dict[str, tuple[Array, Array]]] = IdentityCache(64)


def _sensitivity(cam: ViewCamera, recipe: RecipeConfig, T: Array) -> dict[str, tuple[Array, Array]]:
    """Per mark facing ``cam`` at ``T``: how its image ``[2, 6]`` and its correction ``[2, 6]``
    move per step of the pose (mm along, radians about the part's axes at the marks'
    centroid), by central differences; remembered per camera and pose."""
    T = np.asarray(T, dtype=float)

    def make() -> dict[str, tuple[Array, Array]]:
        ids = [m.id for m in recipe.marks]
        pos = {m.id: np.asarray(m.position, dtype=float) for m in recipe.marks}
        c = np.asarray(recipe.mark_centroid(), dtype=float)
        looks: list[tuple[dict[str, Array], dict[str, Array]]] = []
        for j in range(6):
            for sign in (1.0, -1.0):
                D = np.eye(4)
                if j < 3:
                    D[j, 3] = sign * _STEP_MM
                else:
                    R = rotvec_to_matrix(sign * _STEP_RAD * np.eye(3)[j - 3])
                    D[:3, :3] = R
                    D[:3, 3] = c - R @ c
                Tp = T @ D
                corr = perspective_corrections([(cam, ids)], recipe, Tp)[0]
                uv = {}
                for mid in corr:
                    p = Tp[:3, :3] @ pos[mid] + Tp[:3, 3]
                    p_cf = np.linalg.solve(cam.T_rf_from_cf, np.append(p, 1.0))[:3]
                    uv[mid] = cam.model.project(p_cf[None])[0]
                looks.append((uv, corr))
        out = {}
        for mid in ids:
            if all(mid in corr for _, corr in looks):
                h = np.array([_STEP_MM] * 3 + [_STEP_RAD] * 3)
                B = np.stack([(looks[2 * j][0][mid] - looks[2 * j + 1][0][mid]) / (2 * h[j])
                              for j in range(6)], axis=1)
                A = np.stack([(looks[2 * j][1][mid] - looks[2 * j + 1][1][mid]) / (2 * h[j])
                              for j in range(6)], axis=1)
                out[mid] = (B, A)
        return out

    return _SENSITIVITY.get((cam, recipe), T.tobytes(), make)

