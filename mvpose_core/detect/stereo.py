"""Identity check between the cameras of one view: a mark must lie on its epipolar lines.

A blob taken for the wrong mark (clutter, or a neighbouring mark) in one camera of a stereo pair is
off the epipolar line of the same mark in the other camera. Such marks are dropped in the cameras
that disagree (both, for a pair; with three or more cameras, the one that disagrees with all the
others) and reported; nothing is ever re-assigned.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import combinations

import numpy as np

from mvpose_core.detect.types import MarkDetection
from mvpose_core.scene import ViewCamera
from mvpose_core.transforms import Array, compose, invert


@dataclass(frozen=True)
class EpipolarFailure:
    """A mark whose centres in two cameras of the same view are not epipolar-consistent."""

    mark_id: str
    camera_a: str  # ViewCamera.key
    camera_b: str
    distance_px: float  # mean distance of each centre to the other's epipolar line
    reason: str = "epipolar"


def _skew(t: Array) -> Array:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def epipolar_distance_px(cam_a: ViewCamera, uv_a: Array, cam_b: ViewCamera, uv_b: Array) -> float:
    """Symmetric point-to-epipolar-line distance (px) of one correspondence, distortion removed."""
    T_b_from_a = compose(invert(cam_b.T_rf_from_cf), cam_a.T_rf_from_cf)
    E = _skew(T_b_from_a[:3, 3]) @ T_b_from_a[:3, :3]  # x_b^T E x_a = 0
    xa = np.append(cam_a.model.undistort_normalized(uv_a)[0], 1.0)
    xb = np.append(cam_b.model.undistort_normalized(uv_b)[0], 1.0)
    la, lb = E.T @ xb, E @ xa  # epipolar lines in a and in b
    da = abs(float(la @ xa)) / np.hypot(la[0], la[1]) * cam_a.model.fx
    db = abs(float(lb @ xb)) / np.hypot(lb[0], lb[1]) * cam_b.model.fx
    return 0.5 * (da + db)


def stereo_check(
    detections: Mapping[str, Sequence[MarkDetection]],
    cams: Sequence[ViewCamera],
    max_distance_px: float = 2.0,
) -> tuple[dict[str, list[MarkDetection]], list[EpipolarFailure]]:
    """Check every mark seen by two or more cameras of the same view.

    ``detections`` maps ``ViewCamera.key`` to that camera's detections. Returns the detections
    with inconsistent marks turned into ``found=False, reason="epipolar …"``, and the failures.
    """
    by_key = {c.key: c for c in cams}
    unknown = [k for k in detections if k not in by_key]
    if unknown:
        raise ValueError(f"stereo_check: detections for unknown cameras {unknown}")
    found = {
        k: {d.mark_id: d for d in dets if d.found and d.uv is not None}
        for k, dets in detections.items()
    }
    failures: list[EpipolarFailure] = []
    bad: dict[tuple[str, str], int] = {}  # (camera, mark) -> failed pairs
    pairs: dict[tuple[str, str], int] = {}  # (camera, mark) -> checked pairs
    for ka, kb in combinations(sorted(detections), 2):
        if by_key[ka].view != by_key[kb].view:
            continue
        for mid in sorted(found[ka].keys() & found[kb].keys()):
            d = epipolar_distance_px(by_key[ka], found[ka][mid].uv, by_key[kb], found[kb][mid].uv)  # type: ignore[arg-type]
            for k in (ka, kb):
                pairs[(k, mid)] = pairs.get((k, mid), 0) + 1
            if d > max_distance_px:
                failures.append(EpipolarFailure(mid, ka, kb, d))
                for k in (ka, kb):
                    bad[(k, mid)] = bad.get((k, mid), 0) + 1
    # Drop a mark in a camera that disagrees with every camera it was compared with (in a pair,
    # both cameras); with three or more, the odd one out goes and the consistent ones stay.
    drop = {key for key, n in bad.items() if n == pairs[key]}
    out: dict[str, list[MarkDetection]] = {}
    for k, dets in detections.items():
        out[k] = [
            d.rejected(f"epipolar: inconsistent with another camera of view {by_key[k].view}")
            if (k, d.mark_id) in drop
            else d
            for d in dets
        ]
    return out, failures
