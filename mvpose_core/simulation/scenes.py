"""Synthetic scenes for the accuracy studies: a front-floor-sized part, mark layouts, stereo views.

Geometry (the paper's lab, Section 3.2, and REFERENCE.md): 2048 x 2048 cameras with a 16 mm lens
on 5.5 µm pixels (f = 2909 px, ideal pinhole: distortion is the engine's business, not the
study's); a stereo rig with a 300 mm baseline converging at 1 m; each view puts the rig 1 m
from the marks it looks at. The part is 1500 x 1200 mm (a car front floor), its frame PF in
the middle with z along the surface normal; the part lies about 1.6 m in front of the robot.

Views (one robot pose each) look at the centroid of the marks they see. ``motion="rotate"``
tilts each view 10–25° off the part normal in a random direction and rolls it (the robot
rotates between views, as on a real line); ``motion="translate"`` keeps every view looking
straight down with one orientation (the rig only translates, the paper's Figure 8 setting).

Hand-eye error (paper Section 3.1, Figure 7) is an independent rigid error of each view's rig
pose, N(0, σ²) per axis in rotation and translation, about the rig's own frame. The first view
is exact: the paper expresses the pose in the first camera frame CF1 (eq. 6), where an error
common to the reference and the measurement cancels, so only the errors of the other views
*relative to the first* reach the result.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.spatial.transform import Rotation

from mvpose_core.camera import CameraModel
from mvpose_core.scene import ViewCamera
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import Array, make_transform, zyx_to_matrix
from mvpose_core.uncertainty import LayoutEntry

#: the paper's cameras: 16 mm lens, 5.5 µm pixels, 2048 x 2048
CAMERA = CameraModel(
    fx=16.0 / 0.0055, fy=16.0 / 0.0055, cx=1023.5, cy=1023.5, width=2048, height=2048
)
BASELINE_MM = 300.0
STANDOFF_MM = 1000.0
#: front floor footprint (length x width) and surface relief
PART_SIZE_MM = (1500.0, 1200.0)
RELIEF_MM = 50.0
#: random layouts keep marks at least this far apart (a detector cannot separate closer ones)
MIN_SPACING_MM = 80.0
#: the taught part pose: 1.65 m in front of the robot, 300 mm below its base, turned 4°
T_RF_FROM_PF0 = make_transform(zyx_to_matrix(4.0, 0.0, 0.0), [1650.0, 80.0, -300.0])
#: how far a part lies off its taught place in a trial (uniform per axis)
DISPLACEMENT_MM = 10.0
DISPLACEMENT_DEG = 1.0
#: the four marks of the lab's front floor (deploy/stations/lab.yaml), two per view
CAD_MARKS_4 = np.array(
    [
        [550.0, -200.0, 12.0],
        [-550.0, -200.0, 0.0],
        [-550.0, 200.0, -18.0],
        [550.0, 200.0, 25.0],
    ]
)

Motion = Literal["rotate", "translate"]


@dataclass(frozen=True)
class Trial:
    """One synthetic measurement: the truth, and the cameras as the estimator believes them."""

    marks_pf: dict[str, Array]
    layout: list[LayoutEntry]  # (view, camera_id, mark_id), every sighting
    cameras_true: list[ViewCamera]
    cameras_believed: list[ViewCamera]  # with hand-eye error; equal to the truth without
    T_rf_from_pf: Array  # the part's true pose


def random_layout(
    n_marks: int,
    rng: np.random.Generator,
    size_mm: tuple[float, float] = PART_SIZE_MM,
    relief_mm: float = RELIEF_MM,
    min_spacing_mm: float = MIN_SPACING_MM,
) -> Array:
    """``n_marks`` positions ``[N, 3]`` (PF, mm), uniform on the part, ``min_spacing_mm`` apart."""
    if n_marks < 1:
        raise ValueError(f"n_marks must be ≥ 1, got {n_marks}")
    half = np.array(size_mm) / 2.0
    # Hexagonal packing is the densest layout: more marks than that cannot be placed at all.
    densest = (
        (size_mm[0] + min_spacing_mm)
        * (size_mm[1] + min_spacing_mm)
        / (math.sqrt(3.0) / 2.0 * min_spacing_mm**2)
    )
    if n_marks > densest:
        raise ValueError(
            f"cannot place {n_marks} marks {min_spacing_mm} mm apart on a {size_mm} mm part "
            f"(at most {int(densest)})"
        )
    kept = np.empty((0, 3))
    # Dart throwing: candidates are drawn in batches and accepted in order if far enough from
    # every mark accepted before (the same law as one candidate at a time, far fewer numpy calls).
    for _ in range(200):
        batch = np.column_stack(
            [
                rng.uniform(-half, half, (4 * n_marks, 2)),
                rng.uniform(-relief_mm, relief_mm, 4 * n_marks),
            ]
        )
        pts = np.concatenate([kept, batch])
        first = len(kept)
        d2 = np.sum((pts[:, None, :2] - pts[None, :, :2]) ** 2, axis=2)
        close = d2 < min_spacing_mm**2
        accepted = list(range(first))
        for i in range(first, len(pts)):
            if not close[i, accepted].any():
                accepted.append(i)
                if len(accepted) == n_marks:
                    return pts[accepted]
        kept = pts[accepted]
    raise ValueError(
        f"cannot place {n_marks} marks {min_spacing_mm} mm apart on a {size_mm} mm part"
    )


def split_marks(positions: Array, n_views: int) -> list[list[int]]:
    """Mark indices each view sees: contiguous strips along the part's length.

    Every mark is seen by one view while there are at least as many marks as views; with more
    views than marks, the list of marks is repeated so that every view sees one mark (a few
    marks are then seen twice).
    """
    if n_views < 1:
        raise ValueError(f"n_views must be ≥ 1, got {n_views}")
    order = np.argsort(positions[:, 0], kind="stable")
    sightings = [int(order[i % len(order)]) for i in range(max(len(order), n_views))]
    bounds = np.linspace(0, len(sightings), n_views + 1).round().astype(int)
    return [sightings[bounds[v] : bounds[v + 1]] for v in range(n_views)]


def stereo_rig() -> tuple[Array, Array]:
    """``T_rig_from_cf`` of the left and right camera: toed in to converge at the standoff."""
    half = BASELINE_MM / 2.0
    toe = math.degrees(math.atan2(half, STANDOFF_MM))
    left = make_transform(zyx_to_matrix(0.0, toe, 0.0), [-half, 0.0, 0.0])
    right = make_transform(zyx_to_matrix(0.0, -toe, 0.0), [half, 0.0, 0.0])
    return left, right


def view_poses_pf(targets_pf: Array, motion: Motion, rng: np.random.Generator) -> Array:
    """``T_pf_from_rig`` ``[V, 4, 4]`` of views looking at ``targets_pf`` ``[V, 3]``."""
    n = targets_pf.shape[0]
    if motion == "translate":
        direction = np.tile([0.0, 0.0, 1.0], (n, 1))
        up = np.tile([0.0, 1.0, 0.0], (n, 1))
    elif motion == "rotate":
        tilt = np.radians(rng.uniform(10.0, 25.0, n))
        azimuth = rng.uniform(0.0, 2.0 * math.pi, n)
        direction = np.column_stack(
            [np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)]
        )
        roll = np.radians(rng.uniform(60.0, 120.0, n))
        up = np.column_stack([np.cos(roll), np.sin(roll), np.zeros(n)])
    else:
        raise ValueError(f"motion must be 'rotate' or 'translate', got {motion!r}")
    # Look at the targets, z forward and y down in the image; all views in one numpy call each.
    z = -direction
    x = np.cross(up, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = np.stack([x, np.cross(z, x), z], axis=2)
    T[:, :3, 3] = targets_pf + STANDOFF_MM * direction
    T[:, 3, 3] = 1.0
    return T


def rig_errors(rng: np.random.Generator, n: int, rot_deg: float, trans_mm: float) -> Array:
    """``n`` random rigid errors ``Exp(ω, v)`` ``[n, 4, 4]``, N(0, σ²) per axis (deg, mm)."""
    T = np.tile(np.eye(4), (n, 1, 1))
    if rot_deg > 0:
        T[:, :3, :3] = Rotation.from_rotvec(
            rng.normal(0.0, math.radians(rot_deg), (n, 3))
        ).as_matrix()
    if trans_mm > 0:
        T[:, :3, 3] = rng.normal(0.0, trans_mm, (n, 3))
    return T


def build_trial(
    marks_pf: Array,
    n_views: int,
    rng: np.random.Generator,
    motion: Motion = "rotate",
    handeye_deg: float = 0.0,
    handeye_mm: float = 0.0,
    groups: Sequence[Sequence[int]] | None = None,
) -> Trial:
    """A trial: the part displaced off its taught pose, ``n_views`` stereo views of its marks.

    ``groups`` (mark indices per view) defaults to :func:`split_marks`.
    """
    groups = list(groups) if groups is not None else split_marks(marks_pf, n_views)
    ids = [f"M{i + 1}" for i in range(len(marks_pf))]
    T_true = T_RF_FROM_PF0 @ random_displacement(rng, DISPLACEMENT_MM, DISPLACEMENT_DEG)
    targets = np.array([marks_pf[list(g)].mean(axis=0) for g in groups])
    # Views are planned on the taught part pose: the robot does not know the displacement.
    T_rf_from_rig = T_RF_FROM_PF0 @ view_poses_pf(targets, motion, rng)
    err = np.concatenate(
        [np.eye(4)[None], rig_errors(rng, len(groups) - 1, handeye_deg, handeye_mm)]
    )
    T_rf_from_rig_believed = T_rf_from_rig @ err
    rig = np.stack(stereo_rig())  # [2, 4, 4] T_rig_from_cf
    T_true_cf = T_rf_from_rig[:, None] @ rig[None]  # [V, 2, 4, 4]
    T_believed_cf = T_rf_from_rig_believed[:, None] @ rig[None]
    true: list[ViewCamera] = []
    believed: list[ViewCamera] = []
    layout: list[LayoutEntry] = []
    for v, group in enumerate(groups):
        for pos, cid in enumerate(("left", "right")):
            true.append(ViewCamera(v + 1, cid, CAMERA, T_true_cf[v, pos], "stereo", pos))
            believed.append(ViewCamera(v + 1, cid, CAMERA, T_believed_cf[v, pos], "stereo", pos))
            layout.extend((v + 1, cid, ids[m]) for m in dict.fromkeys(group))
    return Trial(dict(zip(ids, marks_pf, strict=True)), layout, true, believed, T_true)
