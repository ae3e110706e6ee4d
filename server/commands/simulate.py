"""``mvpose simulate``: the paper's accuracy studies (Section 3.1) and station planning."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from mvpose_core.simulation.montecarlo import run_points, summarise
from mvpose_core.simulation.planning import PlanningError, plan_station
from mvpose_core.simulation.studies import HANDEYE_LEVELS, STUDIES, get_study
from server.cli import CliError, load_station_file, station_recipe
from server.simulation_output import plan_report, plot_study, write_csv

CHOICES = (*STUDIES, "all", "plan")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("study", help=f"one of: {', '.join(CHOICES)}")
    parser.add_argument(
        "--trials", type=int, default=2000, help="Monte Carlo trials per point (default 2000)"
    )
    parser.add_argument("--seed", type=int, default=2020, help="random seed (default 2020)")
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("simulation"),
        help="folder for the CSV and PNG files (default ./simulation)",
    )
    parser.add_argument("--workers", type=int, default=2, help="processes (default 2; 1 = no pool)")
    parser.add_argument("--station", type=Path, help="plan: station YAML file")
    parser.add_argument(
        "--recipe", help="plan: recipe name (default: the station's default recipe)"
    )
    parser.add_argument(
        "--detector-noise",
        type=float,
        metavar="PX",
        help="plan: σ of a mark centre in px (default: the recipe's detector_noise_px)",
    )
    parser.add_argument(
        "--handeye",
        metavar="LEVEL",
        help="plan, robot-mounted rigs: add hand-eye/robot error per view to the Monte Carlo: "
        + ", ".join(f"{k} ({v.rot_deg}°/{v.trans_mm} mm)" for k, v in HANDEYE_LEVELS.items()),
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.study not in CHOICES:
        raise CliError(f"unknown study {args.study!r}; choose one of: {', '.join(CHOICES)}")
    if args.trials < 1:
        raise CliError(f"--trials must be at least 1, got {args.trials}")
    if args.seed < 0:
        raise CliError(f"--seed must be ≥ 0, got {args.seed}")
    if args.workers < 1:
        raise CliError(f"--workers must be at least 1, got {args.workers}")
    if args.study == "plan":
        return _plan(args)
    for name in ("station", "recipe", "detector_noise", "handeye"):
        if getattr(args, name) is not None:
            raise CliError(
                f"--{name.replace('_', '-')} applies to 'plan' only, not to study {args.study!r}"
            )
    return _studies(args)


def _studies(args: argparse.Namespace) -> int:
    studies = list(STUDIES.values()) if args.study == "all" else [get_study(args.study)]
    points = [p for s in studies for p in s.points]
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise CliError(f"--out {args.out}: cannot create the folder: {err.strerror}") from None
    command = "mvpose simulate " + " ".join(
        [shlex.quote(args.study), f"--trials {args.trials}", f"--seed {args.seed}"]
    )
    with tqdm(
        total=len(points) * args.trials,
        unit="trial",
        desc=args.study,
        disable=args.no_progress,
        file=sys.stderr,
    ) as bar:
        samples = run_points(points, args.trials, args.seed, args.workers, bar.update)
    by_point = dict(zip(points, samples, strict=True))
    for study in studies:
        rows = [r for p in study.points for r in summarise(p, by_point[p])]
        stem = study.name
        write_csv(args.out / f"{stem}.csv", rows)
        plot_study(args.out / f"{stem}.png", study, rows, command)
        print(f"{study.name}: {args.out / (stem + '.csv')}, {args.out / (stem + '.png')}")
        for r in rows:
            if r.objective == "all":
                left = next(
                    q
                    for q in rows
                    if q.objective == "left_only" and q.x == r.x and q.series == r.series
                )
                print(
                    f"  {r.series:18} x={r.x:<5g} RMS {r.rot_rms:.3f}° {r.trans_rms:.3f} mm "
                    f"(std {r.rot_std:.3f}° {r.trans_std:.3f} mm; bound {r.bound_rot:.3f}° "
                    f"{r.bound_trans:.3f} mm; left-only {left.rot_rms:.3f}° "
                    f"{left.trans_rms:.3f} mm)" + (f" failed {r.failed}" if r.failed else "")
                )
    return 0


def _plan(args: argparse.Namespace) -> int:
    if args.station is None:
        raise CliError("plan needs --station FILE")
    noise = args.detector_noise
    if noise is not None and not (np.isfinite(noise) and noise > 0):
        raise CliError(f"--detector-noise must be a positive number of pixels, got {noise}")
    station = load_station_file(args.station)
    recipe = station_recipe(station, args.recipe)
    level = HANDEYE_LEVELS["zero"]
    if args.handeye is not None:
        if args.handeye not in HANDEYE_LEVELS:
            raise CliError(
                f"unknown hand-eye level {args.handeye!r}; "
                f"choose one of: {', '.join(HANDEYE_LEVELS)}"
            )
        level = HANDEYE_LEVELS[args.handeye]
    rng = np.random.default_rng(args.seed)
    with tqdm(
        total=args.trials, unit="trial", desc="plan", disable=args.no_progress, file=sys.stderr
    ) as bar:
        try:
            plan = plan_station(station, recipe, rng, noise, args.trials, bar.update, level)
        except PlanningError as err:
            raise CliError(str(err)) from None
    print(plan_report(plan))
    return 0 if plan.meets_tolerances else 1
