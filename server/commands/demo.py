"""``mvpose demo``: the whole station server on simulated hardware, driven by the PLC twin.

``mvpose demo`` runs station 1 (four simulated 2048 × 2048 cameras, SQLite under ./var/demo,
Modbus/TCP on loopback (EtherNet/IP class 1 I/O with ``--link enip``, S7 with ``--link s7``,
PROFINET with ``--link profinet`` on a veth pair into a network namespace of the demo's own), the
REST API): the PLC twin moves the part to random known displacements (the simulated cameras
render the new position before the trigger), triggers, and the demo prints
per trigger the true and the measured offset, the error, the 1σ and the server's latency. The
operator page and the REST API stay up at the printed address; ``--triggers N`` stops after N
triggers (``--keep-serving``: and keeps serving until Ctrl-C); ``--truth-out FILE`` writes the
true and measured offsets per trigger in the form ``mvpose validate --truth`` reads.

``mvpose demo --engine-only`` is the engine on its own (no cameras, PLC or server): for each
station file it simulates the mark observations every camera would make (with the recipe's
detector noise), runs :func:`mvpose_core.measure.measure` and prints true vs estimated offsets.
That part is :func:`run_engine_demo`, callable on its own; the server demo is
:func:`run_station_demo` (the loop lives in server/loopback.py, shared with tests and bench).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from mvpose_core.estimate import PoseInputError
from mvpose_core.measure import measure
from mvpose_core.offset import base_frame_offset
from mvpose_core.station import StationFileError
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import matrix_to_xyzwpr, transform_error
from server.links import load_station

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_STATIONS = (
    ROOT / "deploy" / "stations" / "lab.yaml",
    ROOT / "deploy" / "stations" / "station1.yaml",
)
STATION_DEMO = ROOT / "deploy" / "stations" / "station1.yaml"


def _fmt(v: np.ndarray) -> str:
    return " ".join(f"{x:8.2f}" for x in v[:3]) + " |" + " ".join(f"{x:6.2f}" for x in v[3:])


def run_engine_demo(
    stations: Sequence[str | Path] = DEFAULT_STATIONS,
    n: int = 10,
    seed: int = 1,
    max_mm: float = 50.0,
    max_deg: float = 5.0,
    out: Callable[[str], None] = print,
) -> int:
    """Measure ``n`` random displacements per station; return the number of NOK or failed ones."""
    rng = np.random.default_rng(seed)
    bad = 0
    for path in stations:
        st = load_station(path)
        rec = st.recipe()
        T0 = rec.T_rf_from_pf0.matrix
        out(
            f"\n{st.name}: {len(st.cameras)} cameras, {len(st.views)} view(s), recipe {rec.name} "
            f"({len(rec.marks)} marks), detector noise {rec.detector_noise_px} px"
        )
        out(
            f"{'#':>2}  {'base-frame offset (FANUC X Y Z mm | W P R deg)':<52}"
            f"{'error at grasp':>18}   1σ at grasp        gate"
        )
        errs = []
        for i in range(1, n + 1):
            T = T0 @ random_displacement(rng, max_mm, max_deg)
            obs = synthetic_observations(st, rec, T, rng, rec.detector_noise_px)
            try:
                m = measure(st, rec, obs)
            except PoseInputError as err:
                out(f"{i:2d}  estimation refused its input: {err}")
                bad += 1
                continue
            truth = base_frame_offset(T, T0)
            # Error where it matters: at the grasp point (the offset's own translation carries
            # the rotation error times the distance to the robot base).
            G = rec.T_pf_from_grasp.matrix
            rot, trans = transform_error(m.T_rf_from_pf @ G, T @ G)
            errs.append((rot, trans))
            bad += not m.gate.ok
            out(f"{i:2d}  true {_fmt(matrix_to_xyzwpr(truth))}")
            out(
                f"    est  {_fmt(m.offset)}  {rot:6.3f}° {trans:6.3f} mm   "
                f"{m.sigma_rot_deg:5.3f}° {m.sigma_trans_mm:5.3f} mm  "
                f"{'OK' if m.gate.ok else 'NOK ' + m.gate.reason.name}"
            )
        if errs:
            e = np.sqrt(np.mean(np.square(errs), axis=0))
            out(f"    RMS error over {len(errs)} displacements: {e[0]:.4f}° {e[1]:.3f} mm")
    return bad


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "stations",
        nargs="*",
        type=Path,
        help="station file (default deploy/stations/station1.yaml; with --engine-only: files, "
        "default lab and station1)",
    )
    parser.add_argument("--engine-only", action="store_true",
                        help="the pose engine alone on synthetic observations (no server)")
    parser.add_argument("--triggers", type=int, default=None,
                        help="stop after N triggers (default: trigger until Ctrl-C)")
    parser.add_argument("--keep-serving", action="store_true",
                        help="with --triggers: keep the operator page and the REST API up "
                        "afterwards, until Ctrl-C")
    parser.add_argument("--truth-out", type=Path, default=None, metavar="FILE",
                        help="write the true and the measured offset of every trigger to FILE "
                        "(CSV, a row per trigger as it is answered; `mvpose validate --truth` "
                        "reads it)")
    parser.add_argument("-n", type=int, default=10,
                        help="--engine-only: displacements per station (default 10)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--max-mm", type=float, default=None,
                        help="displacement per axis, mm (default 20; engine-only 50)")
    parser.add_argument("--max-deg", type=float, default=None,
                        help="rotation per axis, deg (default 2; engine-only 5)")
    parser.add_argument("--port", type=int, default=8000,
                        help="REST port (default 8000, a free one if taken; 0 = any)")
    parser.add_argument("--data-dir", type=Path, default=Path("var") / "demo",
                        help="SQLite store and image archive (default ./var/demo)")
    from server.plc_buses import BUSES

    parser.add_argument("--link", choices=sorted(BUSES), default="modbus",
                        help="the fieldbus between the PLC twin and the station (default "
                        "modbus; enip: EtherNet/IP class 1 I/O; s7: the station polls a "
                        "simulated S7 CPU's DBs; profinet: the station is an IO-device on a "
                        "veth pair, our IO-controller in a network namespace, root needed)")


def run(args: argparse.Namespace) -> int:
    from server.cli import CliError

    if args.n < 1:
        raise CliError(f"-n must be at least 1, got {args.n}")
    if args.triggers is not None and args.triggers < 1:
        raise CliError(f"--triggers must be at least 1, got {args.triggers}")
    if args.engine_only and args.truth_out is not None:
        raise CliError("--truth-out is for the server demo (without --engine-only)")
    try:
        if args.engine_only:
            bad = run_engine_demo(args.stations or DEFAULT_STATIONS, args.n, args.seed,
                                  50.0 if args.max_mm is None else args.max_mm,
                                  5.0 if args.max_deg is None else args.max_deg)
        else:
            from server.demo_station import run_station_demo

            if len(args.stations) > 1:
                raise CliError("the server demo runs one station file")
            bad = run_station_demo(
                args.stations[0] if args.stations else STATION_DEMO, args.triggers,
                keep_serving=args.keep_serving, seed=args.seed, port=args.port,
                data_dir=args.data_dir,
                max_mm=20.0 if args.max_mm is None else args.max_mm,
                max_deg=2.0 if args.max_deg is None else args.max_deg,
                truth=args.truth_out, link=args.link,
            )
    except StationFileError as err:
        raise CliError(str(err)) from None
    except ValueError as err:  # e.g. a displacement that moves a mark out of an image
        raise CliError(str(err)) from None
    sys.stdout.flush()
    return 1 if bad else 0
