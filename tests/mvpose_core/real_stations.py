"""Test stations like the real ones of issue 16, as data: marks of several diameters, a car-body
part frame far from the marks, a camera tilted 35°, strong lens distortion.

Each builder gives the station file's content (a dict, validated by ``parse_station``) for one
physical station; ``body_mm`` moves the part frame PF away from the marks (a car-body frame:
``body_mm = 1700`` puts its origin 1.7 m from the marks' centroid) without moving anything in
the cell: the marks' positions in PF and the taught pose ``T_rf_from_pf0`` change together.
Images are 1024 x 1024 (8 mm lens on 5.5 µm pixels), so rendering stays fast in tests.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mvpose_core.station import StationConfig, parse_station
from mvpose_core.transforms import (
    apply,
    compose,
    invert,
    make_transform,
    matrix_to_xyzwpr,
    zyx_to_matrix,
)

F_PX = 8.0 / 0.0055  # 1455 px
SIZE = 1024
#: strong barrel distortion (k1 k2 p1 p2 k3): ~25 px at the image corners
DIST = [-0.28, 0.14, 0.0004, -0.0003, -0.03]


def pose(T: np.ndarray) -> dict[str, list[float]]:
    v = matrix_to_xyzwpr(T)
    return {"xyz": [float(x) for x in v[:3]], "wpr": [float(x) for x in v[3:]]}


def look_at(eye: np.ndarray, target: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """T_rf_from_cf of a camera at ``eye`` looking at ``target`` (z forward)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(up_hint, z)
    x = x / np.linalg.norm(x)
    return make_transform(np.stack([x, np.cross(z, x), z], axis=1), eye)


def camera(cid: str) -> dict[str, Any]:
    c = (SIZE - 1) / 2.0
    return {
        "id": cid,
        "driver": {"kind": "sim", "serial": f"SIM-{cid}", "image_noise": 2.0},
        "image_size": [SIZE, SIZE],
        "intrinsics": {"fx": F_PX, "fy": F_PX, "cx": c + 3.0, "cy": c - 2.0},
        "distortion": DIST,
    }


def _body(body_mm: float) -> np.ndarray:
    """T_pf_from_local: where the part-local frame (origin at the marks' centroid) sits in PF."""
    if body_mm == 0.0:
        return np.eye(4)
    d = np.array([0.8, -0.45, 0.4])
    return make_transform(zyx_to_matrix(30.0, -5.0, 8.0), body_mm * d / np.linalg.norm(d))


def _recipe(
    name: str, marks_local: dict[str, tuple[tuple[float, float, float], tuple[float, float, float],
                                            float]],
    T_rf_from_local0: np.ndarray, sightings: list[dict[str, Any]], body_mm: float,
    grasp_local: np.ndarray, **extra: Any,
) -> dict[str, Any]:
    T_pf_from_local = _body(body_mm)
    marks = []
    for mid, (p, n, diameter) in marks_local.items():
        marks.append({
            "id": mid,
            "position": [float(x) for x in apply(T_pf_from_local, np.array([p]))[0]],
            "normal": [float(x) for x in T_pf_from_local[:3, :3] @ np.asarray(n, dtype=float)],
            "diameter_mm": diameter,
        })
    return {
        "name": name,
        "marks": marks,
        "mark_diameter_mm": 12.0,
        "sightings": sightings,
        "T_rf_from_pf0": pose(compose(T_rf_from_local0, invert(T_pf_from_local))),
        "T_pf_from_grasp": pose(compose(T_pf_from_local, grasp_local)),
        "detector_noise_px": 0.05,
        "tolerances": {"rotation_deg": 0.2, "translation_mm": 1.0, "max_offset_mm": 20.0,
                       "max_offset_deg": 2.0},
        **extra,
    }


def bonnet(body_mm: float = 0.0) -> StationConfig:
    """Three fixed cameras, one tilted 35°, see five marks of five diameters on a bonnet."""
    # Part-local frame: origin at the marks' centroid, z out of the (gently curved) surface.
    marks = {
        "M1": ((-210.0, -120.0, -6.0), (-0.06, -0.03, 1.0), 8.0),
        "M2": ((205.0, -125.0, -4.0), (0.05, -0.04, 1.0), 10.0),
        "M3": ((0.0, 10.0, 12.0), (0.0, 0.0, 1.0), 12.0),
        "M4": ((-190.0, 130.0, -3.0), (-0.05, 0.05, 1.0), 16.0),
        "M5": ((195.0, 105.0, 1.0), (0.05, 0.04, 1.0), 20.0),
    }
    T_rf_from_local0 = make_transform(zyx_to_matrix(90.0, 0.0, 180.0), [1400.0, 0.0, 200.0])
    centre = T_rf_from_local0[:3, 3]
    normal = T_rf_from_local0[:3, :3] @ np.array([0.0, 0.0, 1.0])
    side = T_rf_from_local0[:3, :3] @ np.array([1.0, 0.0, 0.0])
    along = T_rf_from_local0[:3, :3] @ np.array([0.0, 1.0, 0.0])
    cams = []
    for cid, tilt, axis, dist in (("top", 12.0, side, 800.0), ("left", -20.0, side, 820.0),
                                  ("tilted", 35.0, along, 780.0)):
        a = np.radians(tilt)
        eye = centre + dist * (np.cos(a) * normal + np.sin(a) * axis)
        cams.append((cid, look_at(eye, centre, along if axis is side else side)))
    T_rf_from_first = cams[0][1]
    station = {
        "name": f"bonnet_{int(body_mm)}",
        "cameras": [camera(cid) for cid, _ in cams],
        "rigs": [{
            "id": "cell", "mount": "fixed", "T_rf_from_rig": pose(T_rf_from_first),
            "cameras": [{"camera": cid, "T_rig_from_cf": pose(compose(invert(T_rf_from_first), T))}
                        for cid, T in cams],
        }],
        "views": [{"id": 1, "rigs": ["cell"]}],
        "recipes": [_recipe(
            "bonnet", marks, T_rf_from_local0,
            [{"view": 1, "camera": cid, "marks": list(marks)} for cid, _ in cams],
            body_mm, make_transform(np.eye(3), [0.0, 0.0, 80.0]),
        )],
    }
    return parse_station(station, f"bonnet(body_mm={body_mm})")


def floor(body_mm: float = 1700.0) -> StationConfig:
    """A robot-mounted stereo pair (200 mm baseline) in two views of four marks of three
    diameters on a front floor; each view's two marks are seen by both cameras."""
    marks = {
        "M1": ((-380.0, -150.0, 0.0), (0.0, 0.0, 1.0), 10.0),
        "M2": ((-380.0, 150.0, 8.0), (0.0, 0.0, 1.0), 14.0),
        "M3": ((380.0, -150.0, -5.0), (0.0, 0.0, 1.0), 20.0),
        "M4": ((380.0, 150.0, 4.0), (0.0, 0.0, 1.0), 14.0),
    }
    T_rf_from_local0 = make_transform(zyx_to_matrix(0.0, 0.0, 180.0), [1500.0, 0.0, -250.0])
    half = 100.0
    toe = np.degrees(np.arctan2(half, 750.0))
    T_rig_from_left = make_transform(zyx_to_matrix(0.0, toe, 0.0), [-half, 0.0, 0.0])
    T_rig_from_right = make_transform(zyx_to_matrix(0.0, -toe, 0.0), [half, 0.0, 0.0])
    T_gf_from_rig = make_transform(zyx_to_matrix(90.0, 0.0, 0.0), [0.0, 100.0, 150.0])
    views = []
    for vid, x in ((1, -380.0), (2, 380.0)):
        target = apply(T_rf_from_local0, np.array([[x, 0.0, 0.0]]))[0]
        tilt = np.radians(10.0 if vid == 1 else -8.0)
        n = T_rf_from_local0[:3, :3] @ np.array([np.sin(tilt), 0.0, np.cos(tilt)])
        T_rf_from_rig = look_at(target + 750.0 * n, target, np.array([1.0, 0.0, 0.0]))
        views.append({"id": vid, "rigs": ["stereo"],
                      "T_rf_from_gf": pose(compose(T_rf_from_rig, invert(T_gf_from_rig)))})
    station = {
        "name": f"floor_{int(body_mm)}",
        "cameras": [camera("left"), camera("right")],
        "rigs": [{"id": "stereo", "mount": "robot", "T_gf_from_rig": pose(T_gf_from_rig),
                  "cameras": [{"camera": "left", "T_rig_from_cf": pose(T_rig_from_left)},
                              {"camera": "right", "T_rig_from_cf": pose(T_rig_from_right)}]}],
        "views": views,
        "recipes": [_recipe(
            "front_floor", marks, T_rf_from_local0,
            [{"view": 1, "camera": c, "marks": ["M1", "M2"]} for c in ("left", "right")]
            + [{"view": 2, "camera": c, "marks": ["M3", "M4"]} for c in ("left", "right")],
            body_mm, make_transform(np.eye(3), [0.0, 0.0, 100.0]),
        )],
    }
    return parse_station(station, f"floor(body_mm={body_mm})")


#: the steep camera of issue 26: 12 mm lens on 3.45 µm pixels, 2048 x 2048, mild barrel distortion
STEEP_F_PX = 12.0 / 0.00345  # 3478 px
STEEP_SIZE = 2048
STEEP_DIST = [-0.11, 0.02, 0.0, 0.0, 0.0]


def compact(body_mm: float = 0.0) -> StationConfig:
    """A compact panel seen by four fixed cameras: three ordinary ones, and one tilted 35° with a
    12 mm lens that sees a 14 mm mark (M2, ~25 px radius) near its lower frame edge (v ≈ 1620
    of 2048), where the lens's distortion and the perspective are strongest."""
    marks = {
        "M1": ((-150.0, -90.0, -2.0), (-0.03, -0.02, 1.0), 10.0),
        "M2": ((140.0, -85.0, 3.0), (0.03, -0.02, 1.0), 14.0),
        "M3": ((-135.0, 95.0, 1.0), (-0.02, 0.03, 1.0), 12.0),
        "M4": ((150.0, 80.0, -3.0), (0.02, 0.03, 1.0), 16.0),
    }
    T_rf_from_local0 = make_transform(zyx_to_matrix(90.0, 0.0, 180.0), [1300.0, 0.0, 150.0])
    R0 = T_rf_from_local0[:3, :3]
    centre = T_rf_from_local0[:3, 3]
    normal, side, along = R0[:, 2], R0[:, 0], R0[:, 1]
    cams = []
    for cid, tilt, axis, dist in (("top", 8.0, side, 760.0), ("left", -18.0, side, 780.0),
                                  ("right", 20.0, along, 760.0)):
        a = np.radians(tilt)
        eye = centre + dist * (np.cos(a) * normal + np.sin(a) * axis)
        cams.append((cid, look_at(eye, centre, along if axis is side else side)))
    # The steep camera: 35° off the normal (tilted across the panel's long side), ~0.92 m from
    # M2, turned so that M2 comes out at v ≈ 1620.
    m2 = apply(T_rf_from_local0, np.array([marks["M2"][0]]))[0]
    a = np.radians(35.0)
    eye = m2 + 920.0 * (np.cos(a) * normal - np.sin(a) * along)
    T = look_at(eye, m2, side)
    down = np.arctan2(1620.0 - (STEEP_SIZE - 1) / 2.0, STEEP_F_PX)
    c, s = np.cos(down), np.sin(down)
    cams.append(("steep", compose(T, make_transform(
        np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]), [0.0, 0.0, 0.0]))))
    T_rf_from_first = cams[0][1]
    steep = camera("steep")
    steep.update({
        "image_size": [STEEP_SIZE, STEEP_SIZE],
        "intrinsics": {"fx": STEEP_F_PX, "fy": STEEP_F_PX, "cx": (STEEP_SIZE - 1) / 2.0 - 4.0,
                       "cy": (STEEP_SIZE - 1) / 2.0 + 3.0},
        "distortion": STEEP_DIST,
    })
    station = {
        "name": f"compact_{int(body_mm)}",
        "cameras": [camera(cid) for cid, _ in cams[:3]] + [steep],
        "rigs": [{
            "id": "cell", "mount": "fixed", "T_rf_from_rig": pose(T_rf_from_first),
            "cameras": [{"camera": cid, "T_rig_from_cf": pose(compose(invert(T_rf_from_first), T))}
                        for cid, T in cams],
        }],
        "views": [{"id": 1, "rigs": ["cell"]}],
        "recipes": [_recipe(
            "compact", marks, T_rf_from_local0,
            [{"view": 1, "camera": cid, "marks": list(marks)} for cid, _ in cams[:3]]
            + [{"view": 1, "camera": "steep", "marks": ["M2"]}],
            body_mm, make_transform(np.eye(3), [0.0, 0.0, 60.0]),
        )],
    }
    return parse_station(station, f"compact(body_mm={body_mm})")
