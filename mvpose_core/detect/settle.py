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
from functools import partial

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
    pose, :func:`sensitivities`) moves each correction by its own sensitivity times that step.
    ~70 µs once the sensitivities are known, against the ~0.6 ms of :func:`settled` and the
    ~1 ms of the server's second measurement; a part that moved mostly in a direction the
    correction does not feel is measured once without it."""
    sens = sensitivities([cam for cam, _ in offsets], recipe, T)
    B: list[Array] = []
    A: list[Array] = []
    d: list[Array] = []
    for (_, off), per in zip(offsets, sens, strict=True):
        for mid, du in off.items():
            if mid in per:
                B.append(per[mid][0])
                A.append(per[mid][1])
                d.append(du)
    if len(d) < 3:
        return True  # too few marks to tell: as without the check
    step = np.linalg.lstsq(np.concatenate(B), np.concatenate(d), rcond=None)[0]
    moved = np.stack(A) @ step
    return bool(np.sqrt(np.einsum("ni,ni->n", moved, moved).max()) > SETTLE_CORR_PX)


_Sensitivity = dict[str, tuple[Array, Array]]
_SENSITIVITY: IdentityCache[_Sensitivity] = IdentityCache(64)


def sensitivities(cams: Sequence[ViewCamera], recipe: RecipeConfig, T: Array,
                  ) -> list[_Sensitivity]:
    """Per camera, per mark facing it at ``T``: how its image ``[2, 6]`` and its correction
    ``[2, 6]`` move per step of the pose (mm along, radians about the part's axes at the
    marks' centroid), by central differences. Remembered per camera place (view, camera, rig,
    lens: a camera re-posed by a robot's flange pose, a few mm off its taught one, uses its
    place's) and pose; those not known are computed together (~3 ms for station 1's four
    cameras; the server's warm-up computes them at the reference)."""
    T = np.asarray(T, dtype=float)
    key = T.tobytes()
    out: list[_Sensitivity | None] = [
        _SENSITIVITY.peek((recipe,), (_place(c), key)) for c in cams]
    todo = [k for k, v in enumerate(out) if v is None]
    if todo:
        made = _differences([cams[k] for k in todo], recipe, T)
        for k, v in zip(todo, made, strict=True):
            out[k] = _SENSITIVITY.get((recipe,), (_place(cams[k]), key), partial(_same, v))
    return [v for v in out if v is not None]


def _differences(cams: Sequence[ViewCamera], recipe: RecipeConfig, T: Array,
                 ) -> list[_Sensitivity]:
    ids = [m.id for m in recipe.marks]
    pos = np.array([m.position for m in recipe.marks], dtype=float)
    c = np.asarray(recipe.mark_centroid(), dtype=float)
    h = np.array([_STEP_MM] * 3 + [_STEP_RAD] * 3)
    # per pose step (+, −) of each axis: every camera's images and corrections
    looks: list[tuple[list[Array], list[dict[str, Array]]]] = []
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
            corr = perspective_corrections([(cam, ids) for cam in cams], recipe, Tp)
            p_rf = pos @ Tp[:3, :3].T + Tp[:3, 3]
            uv = []
            for cam in cams:
                Tc = cam.T_rf_from_cf
                p_cf = (p_rf - Tc[:3, 3]) @ Tc[:3, :3]
                ok = p_cf[:, 2] > 1.0
                u = np.full((len(ids), 2), np.nan)
                u[ok] = cam.model.project(p_cf[ok])
                uv.append(u)
            looks.append((uv, corr))
    out: list[_Sensitivity] = []
    for n in range(len(cams)):
        per: _Sensitivity = {}
        for m, mid in enumerate(ids):
            if not all(mid in corr[n] for _, corr in looks):
                continue
            B = np.stack([(looks[2 * j][0][n][m] - looks[2 * j + 1][0][n][m]) / (2 * h[j])
                          for j in range(6)], axis=1)
            A = np.stack([(looks[2 * j][1][n][mid] - looks[2 * j + 1][1][n][mid]) / (2 * h[j])
                          for j in range(6)], axis=1)
            per[mid] = (B, A)
        out.append(per)
    return out


def _place(cam: ViewCamera) -> tuple[object, ...]:
    """A camera place: its view, camera, rig and lens (by value), whatever its pose."""
    return (cam.view, cam.camera_id, cam.rig_id, cam.rig_position, cam.model)


def _same(v: _Sensitivity) -> _Sensitivity:
    return v

