"""A minimal scene for detector tests and benchmarks: one camera facing a tilted plate of marks."""

from __future__ import annotations

import numpy as np

from mvpose_core.camera import CameraModel
from mvpose_core.scene import ViewCamera
from mvpose_core.station import MarkConfig, Pose, RecipeConfig, Sighting, Tolerances
from mvpose_core.transforms import make_transform, matrix_to_xyzwpr, zyx_to_matrix

CAMERA_ID = "cam"


def plate_scene(
    width: int = 640,
    height: int = 480,
    f_px: float = 2909.1,
    distance_mm: float = 1000.0,
    tilt_deg: float = 0.0,
    mark_diameter_mm: float = 12.0,
    grid: tuple[int, int] = (3, 2),
    pitch_mm: float = 40.0,
    polarity: str = "dark_on_light",
    dist: tuple[float, ...] = (-0.08, 0.12, 0.0002, -0.0001, 0.0),
    max_offset_mm: float = 10.0,
    max_offset_deg: float = 2.0,
) -> tuple[ViewCamera, RecipeConfig]:
    """A camera at the RF origin looking along +z at a plate ``distance_mm`` away.

    The plate (PF, marks on its z = 0 face, normal +z) is rotated ``tilt_deg`` about the camera's
    x axis, so every mark is seen at that tilt; marks sit on a ``grid`` (columns, rows) with
    ``pitch_mm`` spacing around the optical axis. The part's reference pose is the recipe's
    ``T_rf_from_pf0``.
    """
    if not 0.0 <= tilt_deg < 80.0:
        raise ValueError(f"tilt_deg must be in [0, 80), got {tilt_deg}")
    model = CameraModel(
        fx=f_px,
        fy=f_px,
        cx=(width - 1) / 2.0,
        cy=(height - 1) / 2.0,
        width=width,
        height=height,
        dist=dist,
    )
    cam = ViewCamera(view=1, camera_id=CAMERA_ID, model=model, T_rf_from_cf=np.eye(4))
    cols, rows = grid
    marks = [
        MarkConfig(
            id=f"M{r * cols + c + 1}",
            position=((c - (cols - 1) / 2.0) * pitch_mm, (r - (rows - 1) / 2.0) * pitch_mm, 0.0),
        )
        for r in range(rows)
        for c in range(cols)
    ]
    # Rx(180° + tilt): the plate's +z normal points back at the camera, tilted by ``tilt_deg``.
    R = zyx_to_matrix(0.0, 0.0, 180.0 + tilt_deg)
    T_rf_from_pf0 = make_transform(R, [0.0, 0.0, distance_mm])
    v = matrix_to_xyzwpr(T_rf_from_pf0)
    recipe = RecipeConfig(
        name="plate",
        marks=marks,
        mark_diameter_mm=mark_diameter_mm,
        polarity=polarity,
        sightings=[Sighting(view=1, camera=CAMERA_ID, marks=[m.id for m in marks])],
        T_rf_from_pf0=Pose(xyz=tuple(v[:3]), wpr=tuple(v[3:])),
        tolerances=Tolerances(max_offset_mm=max_offset_mm, max_offset_deg=max_offset_deg),
    )
    return cam, recipe
