"""``mvpose validate``: commissioning validation of a station against ground-truth offsets (CSV)."""

from __future__ import annotations

import argparse
from pathlib import Path

from server.cli import CliError, load_station_file, station_recipe
from server.validation import ValidationError, read_offsets_csv, validate_offsets


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--station", required=True, type=Path, help="station YAML file")
    parser.add_argument("--recipe", help="recipe name (default: the station's default recipe)")
    parser.add_argument(
        "--truth", required=True, type=Path,
        help="ground-truth offsets CSV (robot teaching or tooling read-outs): a key column "
        "(index, trigger_id or part_id) and the recipe convention's columns, e.g. X Y Z W P R",
    )
    parser.add_argument(
        "--measured", required=True, type=Path,
        help="measured offsets CSV, e.g. the station's measurement export, same key column",
    )
    parser.add_argument("--key", help="key column (default: first of index, key, trigger_id, "
                        "part_id, id present in each file)")
    parser.add_argument("--out", type=Path, help="write the per-measurement errors as CSV here")


def run(args: argparse.Namespace) -> int:
    station = load_station_file(args.station)
    recipe = station_recipe(station, args.recipe)
    try:
        truth = read_offsets_csv(args.truth, recipe, args.key)
        measured = read_offsets_csv(args.measured, recipe, args.key)
        report = validate_offsets(truth, measured, recipe)
    except ValidationError as err:
        raise CliError(str(err)) from None
    print(report.table())
    if args.out is not None:
        args.out.write_text(report.to_csv(), encoding="utf-8")
        print(f"per-measurement errors written to {args.out}")
    return 0 if report.passed else 1
