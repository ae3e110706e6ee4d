"""Station geometry at measurement time: where every camera of every view is, and what it sees.

A *view camera* is one camera at one view: the unit that takes one image and contributes
observations. Its pose comes from the station description (paper eq. 11–12 for robot rigs):

    robot rig:  T_rf_from_cf = T_rf_from_gf(view) · T_gf_from_rig · T_rig_from_cf
    fixed rig:  T_rf_from_cf = T_rf_from_rig · T_rig_from_cf

The flange pose of a view is the taught one unless the robot reports its actual pose.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from mvpose_core.camera import CameraModel
from mvpose_core.station import RecipeConfig, StationConfig
from mvpose_core.transforms import Array, apply, compose, invert


@dataclass(frozen=True)
class ViewCamera:
    """One camera at one view, with its pose in the robot base frame."""

    view: int
    camera_id: str
    model: CameraModel
    T_rf_from_cf: Array
    rig_id: str = ""
    #: position of the camera in its rig (0 = the rig's first, "left", camera)
    rig_position: int = 0

    @property
    def key(self) -> str:
        """Stable name, e.g. ``"v1/left"``."""
        return f"v{self.view}/{self.camera_id}"


def view_cameras(
    station: StationConfig,
    flange_poses: Mapping[int, Array] | None = None,
    views: Sequence[int] | None = None,
) -> list[ViewCamera]:
    """Every camera of every view (or of ``views``), posed in RF.

    ``flange_poses`` maps a view id to the robot's actual ``T_rf_from_gf``; views not in it use
    the taught pose from the station file.
    """
    flange_poses = flange_poses or {}
    out: list[ViewCamera] = []
    for v in station.views:
        if views is not None and v.id not in views:
            continue
        for rid in v.rigs:
            rig = station.rig(rid)
            if rig.mount == "robot":
                assert rig.T_gf_from_rig is not None and v.T_rf_from_gf is not None  # validated
                T_rf_from_gf = flange_poses.get(v.id, v.T_rf_from_gf.matrix)
                T_rf_from_rig = compose(T_rf_from_gf, rig.T_gf_from_rig.matrix)
            else:
                assert rig.T_rf_from_rig is not None  # validated
                T_rf_from_rig = rig.T_rf_from_rig.matrix
            for pos, rc in enumerate(rig.cameras):
                out.append(
                    ViewCamera(
                        view=v.id,
                        camera_id=rc.camera,
                        model=station.camera(rc.camera).model,
                        T_rf_from_cf=compose(T_rf_from_rig, rc.T_rig_from_cf.matrix),
                        rig_id=rid,
                        rig_position=pos,
                    )
                )
    return out


def repose(
    cameras: Sequence[ViewCamera], station: StationConfig, flange_poses: Mapping[int, Array]
) -> list[ViewCamera]:
    """``cameras``, posed at their views' taught flange poses, moved to the robot's actual ones.

    The same poses as :func:`view_cameras` with ``flange_poses`` (up to rounding), without
    building the cameras again: a robot-mounted camera keeps its lens model object and gets the
    new pose ``T_rf_from_gf(actual) · T_rf_from_gf(taught)⁻¹ · T_rf_from_cf``; a fixed camera, or
    one of a view without an actual pose, is returned as it is, so that what is remembered for
    it (window predictions, packed camera tables) is found again.
    """
    moves: dict[int, Array] = {}
    for v in station.views:
        actual = flange_poses.get(v.id)
        if actual is not None and v.T_rf_from_gf is not None:
            moves[v.id] = compose(np.asarray(actual, dtype=float), invert(v.T_rf_from_gf.matrix))
    robot = {r.id for r in station.rigs if r.mount == "robot"}
    out: list[ViewCamera] = []
    for cam in cameras:
        move = moves.get(cam.view)
        if move is None or cam.rig_id not in robot:
            out.append(cam)
        else:
            out.append(replace(cam, T_rf_from_cf=compose(move, cam.T_rf_from_cf)))
    return out


def sighted_marks(recipe: RecipeConfig, view: int, camera_id: str) -> list[str]:
    """Mark ids the recipe expects ``camera_id`` to see in ``view`` (empty if none)."""
    out: list[str] = []
    for s in recipe.sightings:
        if s.view == view and s.camera == camera_id:
            out.extend(m for m in s.marks if m not in out)
    return out


@dataclass(frozen=True)
class ProjectedMark:
    """Where a mark's centre lands in an image (renderer truth, detector windows)."""

    mark_id: str
    uv: Array  # [2] distorted pixel of the circle's centre
    depth_mm: float
    p_cf: Array  # [3] centre in the camera frame
    n_cf: Array  # [3] unit surface normal in the camera frame


def project_recipe_marks(
    cam: ViewCamera, recipe: RecipeConfig, T_rf_from_pf: Array, only_sighted: bool = True
) -> list[ProjectedMark]:
    """Project the recipe's marks into one view camera for a part at ``T_rf_from_pf``."""
    ids = (
        sighted_marks(recipe, cam.view, cam.camera_id)
        if only_sighted
        else [m.id for m in recipe.marks]
    )
    if not ids:
        return []
    marks = [recipe.marks[recipe.mark_index(i)] for i in ids]
    T_cf_from_pf = compose(invert(cam.T_rf_from_cf), T_rf_from_pf)
    p_cf = apply(T_cf_from_pf, np.array([m.position for m in marks], dtype=float))
    normals = np.array([m.normal for m in marks], dtype=float)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    n_cf = normals @ T_cf_from_pf[:3, :3].T
    uv = cam.model.project(p_cf)
    return [
        ProjectedMark(
            mark_id=m.id, uv=uv[k], depth_mm=float(p_cf[k, 2]), p_cf=p_cf[k], n_cf=n_cf[k]
        )
        for k, m in enumerate(marks)
    ]
