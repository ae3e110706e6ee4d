"""Rendered images through ``mvpose measure``: does the reported 1σ track the error there too?

For each example station (or ``--station FILE``): N parts within ±10 mm / ±1° of the taught
pose are rendered (mvpose_core.render, default options: image noise, blur, illumination) into the
``mvpose measure`` folder layout, measured by the command itself, and the pose of every OK result
compared with the truth at the recipe's grasp frame: the RMS error against the RMS of the
reported detector part of the 1σ (the example stations set no calibration 1σ).
Run: ``python -m bench.measure_uncertainty [--triggers N] [--station FILE ...]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

from mvpose_core.render import render_view
from mvpose_core.scene import sighted_marks, view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import transform_error
from server.cli import main as mvpose

STATIONS = Path(__file__).resolve().parents[1] / "deploy" / "stations"


def run_station(path: Path, n: int, rng: np.random.Generator, work: Path) -> str:
    st = load_station(path)
    rec = st.recipe()
    images = work / st.name
    truth = {}
    for k in range(1, n + 1):
        T = rec.T_rf_from_pf0.matrix @ random_displacement(rng, 10.0, 1.0)
        key = f"part{k:04d}"
        for cam in view_cameras(st):
            if not sighted_marks(rec, cam.view, cam.camera_id):
                continue
            folder = images / key / (f"v{cam.view}" if st.robot_mounted else "")
            folder.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(folder / f"{cam.camera_id}.png"), render_view(cam, rec, T, rng).image)
        truth[key] = T
    code = mvpose(["measure", "--station", str(path), "--images", str(images), "--quiet"])
    if code != 0:
        return f"{st.name}: mvpose measure exited {code}"
    records = json.loads((images / "measured" / "measurements.json").read_text())
    csv_rows = (images / "measured" / "measurements.csv").read_text().splitlines()
    header = csv_rows[0].split(",")
    by_key = {r.split(",")[0]: dict(zip(header, r.split(","), strict=False)) for r in csv_rows[1:]}
    G = rec.T_pf_from_grasp.matrix
    err, rep, noise = [], [], []
    for r in records:
        if r["result"] != "OK":
            continue
        T = np.array(r["T_rf_from_pf"], dtype=float)
        err.append(transform_error(T @ G, truth[r["part_id"]] @ G))
        row = by_key[r["part_id"]]
        rep.append((float(row["sigma_detector_deg"]), float(row["sigma_detector_mm"])))
        noise.append(float(row["detector_noise_px"]))
    if not err:
        return f"{st.name}: no OK result"
    a = np.sqrt(np.mean(np.square(err), axis=0))
    b = np.sqrt(np.mean(np.square(rep), axis=0))
    return (f"{st.name:<9} {len(err):3d}/{n} OK  detector σ median {np.median(noise):.4f} px  "
            f"actual RMS {a[0]:.5f} deg {a[1]:.4f} mm  reported {b[0]:.5f} deg {b[1]:.4f} mm  "
            f"ratio {b[0] / a[0]:.2f} / {b[1] / a[1]:.2f}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.measure_uncertainty", description=__doc__)
    p.add_argument("--triggers", type=int, default=40)
    p.add_argument("--station", type=Path, action="append")
    p.add_argument("--seed", type=int, default=2026)
    args = p.parse_args(argv)
    files = args.station or [STATIONS / f"{n}.yaml" for n in ("lab", "station1", "station2")]
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory(prefix="mvpose-measure-") as tmp:
        for path in files:
            print(run_station(path, args.triggers, rng, Path(tmp)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
