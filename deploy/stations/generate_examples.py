"""Write the example station files (lab, station1, station2) from plausible geometry.

Run from the repository root: ``python deploy/stations/generate_examples.py``. The geometry follows
the paper's three setups: 2048 x 2048 cameras, 16 mm lenses on 5.5 µm pixels (f ≈ 2909 px), about
1 m from the marks. The files are committed; this script documents where their numbers come from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from mvpose_core.transforms import compose, invert, make_transform, matrix_to_xyzwpr, zyx_to_matrix

HERE = Path(__file__).resolve().parent
F_PX = 16.0 / 0.0055  # 2909 px
INTR = {"fx": round(F_PX, 1), "fy": round(F_PX, 1), "cx": 1023.5, "cy": 1023.5}
DIST = [-0.08, 0.12, 0.0002, -0.0001, 0.0]


def pose(T: np.ndarray) -> dict:
    v = matrix_to_xyzwpr(T)
    return {"xyz": [round(float(x), 4) for x in v[:3]], "wpr": [round(float(x), 6) for x in v[3:]]}


def look_at(eye: np.ndarray, target: np.ndarray, up_hint: np.ndarray) -> np.ndarray:
    """T_rf_from_cf of a camera at ``eye`` looking at ``target`` (z forward, y down in image)."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(up_hint, z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return make_transform(np.stack([x, y, z], axis=1), eye)


def camera(cid: str, serial: str) -> dict:
    return {
        "id": cid,
        "driver": {"kind": "sim", "serial": serial},
        "image_size": [2048, 2048],
        "pixel_format": "mono8",
        "intrinsics": INTR,
        "distortion": DIST,
    }


def tolerances() -> dict:
    return {"rotation_deg": 0.2, "translation_mm": 1.0, "max_rms_px": 1.0, "max_residual_px": 3.0,
            "max_offset_mm": 100.0, "max_offset_deg": 10.0}


def lab() -> dict:
    # Part: a front floor lying about 300 mm below the robot base, 1.6 m in front of it.
    T_rf_from_pf0 = make_transform(zyx_to_matrix(4.0, 0.0, 0.0), [1650.0, 80.0, -300.0])
    marks = {"M1": (550.0, -200.0, 12.0), "M2": (-550.0, -200.0, 0.0),
             "M3": (-550.0, 200.0, -18.0), "M4": (550.0, 200.0, 25.0)}
    # Stereo rig: 300 mm baseline converging at 1 m; rig frame in the middle, z forward.
    half = 150.0
    toe = np.degrees(np.arctan2(half, 1000.0))
    T_rig_from_left = make_transform(zyx_to_matrix(0.0, toe, 0.0), [-half, 0.0, 0.0])
    T_rig_from_right = make_transform(zyx_to_matrix(0.0, -toe, 0.0), [half, 0.0, 0.0])
    T_gf_from_rig = make_transform(zyx_to_matrix(90.0, 0.0, 0.0), [0.0, 120.0, 180.0])
    views = []
    for vid, (cx, tilt) in enumerate([(-550.0, 8.0), (550.0, -6.0)], start=1):
        target = T_rf_from_pf0 @ np.array([cx, 0.0, 0.0, 1.0])
        # The rig looks down from 1 m, tilted a little about the part's y axis (not a pure translation).
        eye = target[:3] + 1000.0 * np.array([np.sin(np.radians(tilt)), 0.0, np.cos(np.radians(tilt))])
        T_rf_from_rig = look_at(eye, target[:3], np.array([0.0, 1.0, 0.0]))
        views.append({"id": vid, "rigs": ["stereo"],
                      "T_rf_from_gf": pose(compose(T_rf_from_rig, invert(T_gf_from_rig)))})
    return {
        "name": "lab",
        "description": "Robot-mounted stereo pair, two views of a front floor (paper Section 3.2)",
        "deadline_ms": 50.0,
        "cameras": [camera("left", "SIM-LAB-L"), camera("right", "SIM-LAB-R")],
        "rigs": [{"id": "stereo", "mount": "robot",
                  "cameras": [{"camera": "left", "T_rig_from_cf": pose(T_rig_from_left)},
                              {"camera": "right", "T_rig_from_cf": pose(T_rig_from_right)}],
                  "T_gf_from_rig": pose(T_gf_from_rig)}],
        "views": views,
        "recipes": [{
            "name": "front_floor", "version": 1,
            "description": "Front floor, 4 marks, two per view",
            "marks": [{"id": k, "position": list(v), "normal": [0.0, 0.0, 1.0]} for k, v in marks.items()],
            "mark_diameter_mm": 12.0, "polarity": "dark_on_light",
            "sightings": [{"view": 1, "camera": "left", "marks": ["M2", "M3"]},
                          {"view": 1, "camera": "right", "marks": ["M2", "M3"]},
                          {"view": 2, "camera": "left", "marks": ["M1", "M4"]},
                          {"view": 2, "camera": "right", "marks": ["M1", "M4"]}],
            "T_rf_from_pf0": pose(T_rf_from_pf0),
            "T_pf_from_grasp": pose(make_transform(np.eye(3), [0.0, 0.0, 150.0])),
            "robot_convention": "fanuc", "detector_noise_px": 0.1,
            "tolerances": tolerances(),
        }],
        "default_recipe": "front_floor",
    }


def fixed_station(name: str, description: str, cams: list[tuple[str, str, list[str]]],
                  marks: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]],
                  T_rf_from_pf0: np.ndarray, recipe: str, diameter: float) -> dict:
    """Fixed cameras, each looking at its marks from about 1 m along a tilted direction."""
    rig_cams = []
    T_rf_from_first = None
    for cid, _serial, seen in cams:
        pts = np.array([marks[m][0] for m in seen])
        nrm = np.mean([marks[m][1] for m in seen], axis=0)
        nrm /= np.linalg.norm(nrm)
        centre_pf = pts.mean(axis=0)
        # Tilt the line of sight 25° away from the normal so the station is not all fronto-parallel.
        side = np.cross(nrm, [0.0, 0.0, 1.0] if abs(nrm[2]) < 0.9 else [1.0, 0.0, 0.0])
        side /= np.linalg.norm(side)
        ang = np.radians(25.0)
        eye_pf = centre_pf + 1000.0 * (np.cos(ang) * nrm + np.sin(ang) * side)
        up = np.array([0.0, 0.0, 1.0]) if abs(nrm[2]) < 0.9 else np.array([0.0, 1.0, 0.0])
        T_pf_from_cf = look_at(eye_pf, centre_pf, up)
        T_rf_from_cf = compose(T_rf_from_pf0, T_pf_from_cf)
        if T_rf_from_first is None:
            T_rf_from_first = T_rf_from_cf
        rig_cams.append({"camera": cid, "T_rig_from_cf": pose(compose(invert(T_rf_from_first), T_rf_from_cf))})
    return {
        "name": name, "description": description, "deadline_ms": 50.0,
        "cameras": [camera(cid, serial) for cid, serial, _ in cams],
        "rigs": [{"id": "cell", "mount": "fixed", "cameras": rig_cams, "T_rf_from_rig": pose(T_rf_from_first)}],
        "views": [{"id": 1, "rigs": ["cell"]}],
        "recipes": [{
            "name": recipe, "version": 1, "description": description,
            "marks": [{"id": k, "position": list(p), "normal": list(n)} for k, (p, n) in marks.items()],
            "mark_diameter_mm": diameter, "polarity": "dark_on_light",
            "sightings": [{"view": 1, "camera": cid, "marks": seen} for cid, _, seen in cams],
            "T_rf_from_pf0": pose(T_rf_from_pf0),
            "T_pf_from_grasp": pose(make_transform(np.eye(3), [0.0, 0.0, 120.0])),
            "robot_convention": "fanuc", "detector_noise_px": 0.1,
            "tolerances": tolerances(),
        }],
        "default_recipe": recipe,
    }


def station1() -> dict:
    up, back = (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0)
    marks = {
        "T1": ((-150.0, -520.0, 40.0), up), "T2": ((150.0, -560.0, 55.0), up),
        "T3": ((-120.0, 540.0, 35.0), up), "T4": ((180.0, 500.0, 60.0), up),
        "B1": ((-800.0, -480.0, -60.0), back), "B2": ((-800.0, -220.0, -20.0), back),
        "B3": ((-800.0, 230.0, -30.0), back), "B4": ((-800.0, 470.0, -70.0), back),
    }
    cams = [("top_left", "SIM-S1-TL", ["T1", "T2"]), ("top_right", "SIM-S1-TR", ["T3", "T4"]),
            ("back_left", "SIM-S1-BL", ["B1", "B2"]), ("back_right", "SIM-S1-BR", ["B3", "B4"])]
    T = make_transform(zyx_to_matrix(90.0, 0.0, 0.0), [1500.0, 0.0, -500.0])
    return fixed_station("station1", "Production station 1: four fixed cameras, two above, two behind "
                         "(paper Section 3.3)", cams, marks, T, "floor_panel", 16.0)


def station2() -> dict:
    up, back = (0.0, 0.0, 1.0), (-1.0, 0.0, 0.0)
    marks = {
        "T1": ((-200.0, -180.0, 30.0), up), "T2": ((160.0, -120.0, 45.0), up), "T3": ((0.0, 210.0, 20.0), up),
        "B1": ((-700.0, -450.0, -40.0), back), "B2": ((-700.0, -200.0, -10.0), back),
        "B3": ((-700.0, 220.0, -20.0), back), "B4": ((-700.0, 460.0, -50.0), back),
    }
    cams = [("top", "SIM-S2-T", ["T1", "T2", "T3"]), ("back_left", "SIM-S2-BL", ["B1", "B2"]),
            ("back_right", "SIM-S2-BR", ["B3", "B4"])]
    T = make_transform(zyx_to_matrix(90.0, 0.0, 0.0), [1400.0, -50.0, -450.0])
    return fixed_station("station2", "Production station 2: three fixed cameras, one above, two behind "
                         "(paper Section 3.3)", cams, marks, T, "bonnet", 14.0)


def main() -> None:
    header = "# Generated by deploy/stations/generate_examples.py; plausible geometry, simulated cameras.\n"
    for name, data in (("lab", lab()), ("station1", station1()), ("station2", station2())):
        (HERE / f"{name}.yaml").write_text(header + yaml.safe_dump(data, sort_keys=False), encoding="utf-8")


if __name__ == "__main__":
    main()
