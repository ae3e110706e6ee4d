"""Stations, camera configs and image folders shared by the camera driver tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import genicam
import numpy as np
import yaml

from mvpose_core.station import CameraConfig, StationConfig, parse_station

ROOT = Path(__file__).resolve().parents[2]
VIKY_CTI = str(Path(genicam.__file__).with_name("viky.cti"))
W, H = 640, 480  # small frames keep the suite fast; every backend is tested at this size


def small_station(
    name: str = "lab", width: int = W, height: int = H, **driver: Any
) -> StationConfig:
    """An example station with its cameras scaled to ``width`` x ``height`` (same field of view)."""
    data = yaml.safe_load((ROOT / "deploy" / "stations" / f"{name}.yaml").read_text())
    for cam in data["cameras"]:
        w0, h0 = cam["image_size"]
        sx, sy = width / w0, height / h0
        i = dict(cam["intrinsics"])
        cam["intrinsics"] = {
            "fx": i["fx"] * sx,
            "fy": i["fy"] * sy,
            "cx": (i["cx"] + 0.5) * sx - 0.5,
            "cy": (i["cy"] + 0.5) * sy - 0.5,
        }
        cam["image_size"] = [width, height]
        cam["driver"] = {**cam["driver"], **driver}
    return parse_station(data, f"{name}.yaml (scaled to {width}x{height})")


def camera_config(camera_id: str, width: int = W, height: int = H, **driver: Any) -> CameraConfig:
    """A camera of any backend with placeholder intrinsics (drivers do not use them)."""
    return CameraConfig.model_validate(
        {
            "id": camera_id,
            "driver": driver,
            "image_size": [width, height],
            "intrinsics": {"fx": 800.0, "fy": 800.0, "cx": width / 2 - 0.5, "cy": height / 2 - 0.5},
        }
    )


def write_images(folder: Path, images: list[np.ndarray], prefix: str = "frame") -> list[Path]:
    """Write lossless PNGs named so that name order is list order."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, image in enumerate(images):
        p = folder / f"{prefix}{k:04d}.png"
        if not cv2.imwrite(str(p), image):
            raise OSError(f"cannot write {p}")
        paths.append(p)
    return paths


def random_images(
    rng: np.random.Generator, n: int, width: int = W, height: int = H
) -> list[np.ndarray]:
    """Distinct uint8 noise images: any mix-up of frames shows in a pixel comparison."""
    return [rng.integers(0, 256, (height, width), dtype=np.uint8) for _ in range(n)]
