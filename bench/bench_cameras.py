"""Camera benchmarks: CaptureGroup overhead on 4 simulated 2048 x 2048 cameras (target <= 1 ms
median), and trigger-to-frame times of pylon's camera emulation and the viky.cti producer."""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from bench.timing import check, measure
from drivers.cameras import CaptureGroup, Frame, SimScene, make_camera
from mvpose_core.station import CameraConfig, load_station

ROOT = Path(__file__).resolve().parents[1]
OVERHEAD_TARGET_MS = 1.0


def _frames_ok(res: Mapping[str, object]) -> None:
    bad = {k: v for k, v in res.items() if not isinstance(v, Frame)}
    if bad:
        raise RuntimeError(f"benchmark grab failed: {bad}")


def bench_sim_group() -> bool:
    station = load_station(ROOT / "deploy" / "stations" / "station1.yaml")
    scene = SimScene(station, None, np.random.default_rng(0))
    t = measure(
        "render 4 x 2048x2048 (SimScene.set_part_pose)",
        lambda: scene.set_part_pose(station.recipe().T_rf_from_pf0.matrix),
        repeat=3,
        warmup=0,
    )
    print(t.line())
    cams = [make_camera(c, scene) for c in station.cameras]  # latency 0: pre-rendered frames
    with CaptureGroup(cams) as group:
        errors = {k: v for k, v in group.wait_ready(10.0).items() if v is not None}
        if errors:
            raise RuntimeError(f"cameras not up: {errors}")
        _frames_ok(group.grab_all(1.0))
        serial = measure(
            "4 cameras one after another, one thread",
            lambda: [(c.trigger(), c.grab(1.0)) for c in cams],
            repeat=300,
        )
        par = measure(
            "CaptureGroup.grab_all, 4 x 2048x2048, parallel",
            lambda: group.grab_all(1.0),
            repeat=500,
        )
    print(serial.line())
    print(par.line(serial))
    return check("grab_all overhead, 4 sim cameras (median)", par.median, OVERHEAD_TARGET_MS)


def bench_trigger_to_frame(label: str, config: CameraConfig) -> None:
    with make_camera(config) as cam:
        cam.arm("software")
        t = measure(label, lambda: (cam.trigger(), cam.grab(2.0)), repeat=40, warmup=3)
    print(t.line())


def main() -> int:
    ok = bench_sim_group()
    os.environ.setdefault("PYLON_CAMEMU", "1")  # before the first pylon enumeration
    with tempfile.TemporaryDirectory() as tmp:
        import cv2

        img = np.random.default_rng(1).integers(0, 256, (2048, 2048), dtype=np.uint8)
        cv2.imwrite(str(Path(tmp) / "f0.png"), img)
        for size, exposure in ((2048, 5000.0), (2048, 100.0), (640, 100.0)):
            cfg = CameraConfig.model_validate(
                {
                    "id": "basler",
                    "image_size": [size, size],
                    "intrinsics": {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0},
                    "driver": {
                        "kind": "pylon",
                        "serial": "0815-0000",
                        "exposure_us": exposure,
                        "features": {
                            "ImageFilename": tmp,
                            "ImageFileMode": "On",
                            "TestImageSelector": "Off",
                        },
                    },
                }
            )
            bench_trigger_to_frame(
                f"pylon emulation trigger->frame {size}x{size}, exp {exposure:g} us", cfg
            )
    import genicam

    cti = str(Path(genicam.__file__).with_name("viky.cti"))
    cfg = CameraConfig.model_validate(
        {
            "id": "viky",
            "image_size": [640, 480],
            "intrinsics": {"fx": 1.0, "fy": 1.0, "cx": 0.0, "cy": 0.0},
            "driver": {"kind": "genicam", "serial": "0", "cti": cti},
        }
    )
    bench_trigger_to_frame("viky.cti emulated trigger->frame 640x480 (200 fps)", cfg)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
