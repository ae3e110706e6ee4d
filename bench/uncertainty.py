"""Does the reported 1σ track the error? Monte Carlo of both parts on the deploy/ stations.

For each example station (or ``--station FILE``): the detector part at pixel noise σ ≠ the
recipe's a-priori ``detector_noise_px`` (observations with N(0, σ²) per coordinate), and the
calibration part with the station's transforms drawn from a stated 1σ (robot repeatability
0.02 mm / 0.004°, rig pose 0.1 mm / 0.015°, camera in rig 0.03 mm / 0.003°, or ``--robot``,
``--rigs``, ``--cameras``; unless the station file sets its own ``uncertainty:``) and measured
with the nominal station. Prints the RMS error
at the grasp point against the RMS reported 1σ (docs/engine.md, "Uncertainty model").
Run: ``python -m bench.uncertainty [--trials N] [--station FILE] [--noise PX ...] [--rigs MM DEG]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mvpose_core.simulation.uncertainty_check import (
    calibration_check,
    detector_check,
    with_calibration_sigma,
)
from mvpose_core.station import load_station
from mvpose_core.uncertainty_settings import PoseSigma

STATIONS = Path(__file__).resolve().parents[1] / "deploy" / "stations"
CALIB = {"robot": PoseSigma(mm=0.02, deg=0.004), "rigs": PoseSigma(mm=0.1, deg=0.015),
         "cameras": PoseSigma(mm=0.03, deg=0.003)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.uncertainty", description=__doc__)
    p.add_argument("--trials", type=int, default=1000)
    p.add_argument("--station", type=Path, action="append", help="station file (default: "
                   "lab, station1, station2 of deploy/stations)")
    p.add_argument("--noise", type=float, nargs="*", default=[0.01, 0.03, 0.1],
                   help="detector noise σ px per coordinate (default 0.01 0.03 0.1; none: skip)")
    for name, what in (("robot", "robot repeatability"), ("rigs", "every rig's pose"),
                       ("cameras", "every camera in its rig")):
        p.add_argument(f"--{name}", type=float, nargs=2, metavar=("MM", "DEG"),
                       help=f"1σ of {what} for the calibration check (default "
                       f"{CALIB[name].mm} {CALIB[name].deg})")
    p.add_argument("--seed", type=int, default=2026)
    args = p.parse_args(argv)
    files = args.station or [STATIONS / f"{n}.yaml" for n in ("lab", "station1", "station2")]
    rng = np.random.default_rng(args.seed)
    calib = {k: PoseSigma(mm=v[0], deg=v[1]) if (v := getattr(args, k)) else CALIB[k]
             for k in CALIB}
    worst = 1.0
    for path in files:
        station = load_station(path)
        recipe = station.recipe()
        print(f"{station.name} (recipe {recipe.name}, a-priori σ {recipe.detector_noise_px} px)")
        for sigma in args.noise:
            with tqdm(total=args.trials, desc=f"detector σ {sigma}", leave=False) as bar:
                chk = detector_check(station, recipe, sigma, args.trials, rng,
                                     progress=bar.update)
            print(f"  σ {sigma:<5} {chk.line()}")
            worst = max(worst, *(max(r, 1 / r) for r in chk.ratio))
        u = station.uncertainty
        drawn = station if (u.rigs or u.cameras or not u.robot_repeatability.is_zero) else (
            with_calibration_sigma(station, **calib))
        with tqdm(total=args.trials, desc="calibration", leave=False) as bar:
            chk = calibration_check(drawn, recipe, args.trials, rng, progress=bar.update)
        print(f"  {'':7} {chk.line()}")
        worst = max(worst, *(max(r, 1 / r) for r in chk.ratio))
    print(f"largest deviation of reported/actual from 1: x{worst:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
