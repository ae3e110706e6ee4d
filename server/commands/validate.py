"""``mvpose validate``: commissioning validation of a station against ground-truth offsets (CSV).

The measured offsets come from the station's export (CSV) or from ``mvpose measure`` /
``mvpose replay`` (their CSV, or the records' JSON). Without ``--key`` the key column is the
first of ``index, key, trigger_id, part_id, id`` that both files have.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from pathlib import Path

from mvpose_core.station import RecipeConfig
from server.cli import CliError, load_station_file, station_recipe
from server.validation import KEY_COLUMNS, ValidationError, read_offsets_csv, validate_offsets


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--station", required=True, type=Path, help="station YAML file")
    parser.add_argument("--recipe", help="recipe name (default: the station's default recipe)")
    parser.add_argument(
        "--truth", required=True, type=Path,
        help="ground-truth offsets CSV (robot teaching or tooling read-outs): a key column "
        "(index, key, trigger_id or part_id) and the recipe convention's columns, e.g. X Y Z W P R",
    )
    parser.add_argument(
        "--measured", required=True, type=Path,
        help="measured offsets: the station's measurement export (CSV), or what mvpose measure / "
        "mvpose replay wrote (measurements.csv, or the records' .json)",
    )
    parser.add_argument("--key", help="key column (default: the first of index, key, trigger_id, "
                        "part_id, id that both files have)")
    parser.add_argument("--out", type=Path, help="write the per-measurement errors as CSV here")


def records_json_as_csv(path: Path, recipe: RecipeConfig) -> io.StringIO:
    """Records (a JSON list, as ``mvpose measure`` writes them or the export's JSON) as CSV text
    with ``key``/``part_id``/``trigger_id`` and the offset of each OK record."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise ValidationError(f"{path}: cannot read: {err.strerror}") from None
    except json.JSONDecodeError as err:
        raise ValidationError(f"{path}: not valid JSON: {err}") from None
    if not isinstance(data, list):
        raise ValidationError(f"{path}: expected a list of measurement records")
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    labels = list(recipe.robot_convention.labels)
    w.writerow(["key", "part_id", "trigger_id", *labels])
    for n, item in enumerate(data, start=1):
        rec = item.get("record", item) if isinstance(item, dict) else None
        if not isinstance(rec, dict):
            raise ValidationError(f"{path}: item {n} is not a measurement record")
        offset = rec.get("offset") if rec.get("result") == "OK" else None
        values = offset.get("values", []) if isinstance(offset, dict) else []
        if offset and offset.get("convention") != recipe.robot_convention.value:
            raise ValidationError(f"{path}: item {n}: offset in {offset.get('convention')!r}, "
                                  f"the recipe uses {recipe.robot_convention.value!r}")
        key = rec.get("part_id") or str(rec.get("trigger_id", n))
        w.writerow([key, rec.get("part_id") or "", rec.get("trigger_id", ""),
                    *(values or [""] * len(labels))])
    buf.name = str(path)  # read_offsets_csv names the source by it
    buf.seek(0)
    return buf


def _header(source: Path | io.StringIO) -> list[str]:
    if isinstance(source, io.StringIO):
        first = source.getvalue().split("\n", 1)[0]
    else:
        try:
            with source.open(encoding="utf-8-sig") as f:
                first = f.readline()
        except OSError as err:
            raise ValidationError(f"{source}: cannot read: {err.strerror}") from None
    return [c.strip().lower() for c in next(csv.reader([first]), [])]


def common_key(truth: Path | io.StringIO, measured: Path | io.StringIO) -> str | None:
    """The first key column both files have (None: let each file pick its own)."""
    a, b = _header(truth), _header(measured)
    return next((k for k in KEY_COLUMNS if k in a and k in b), None)


def run(args: argparse.Namespace) -> int:
    station = load_station_file(args.station)
    recipe = station_recipe(station, args.recipe)
    try:
        measured: Path | io.StringIO = args.measured
        if args.measured.suffix.lower() == ".json":
            measured = records_json_as_csv(args.measured, recipe)
        key = args.key or common_key(args.truth, measured)
        truth = read_offsets_csv(args.truth, recipe, key)
        meas = read_offsets_csv(measured, recipe, key)
        report = validate_offsets(truth, meas, recipe)
    except ValidationError as err:
        raise CliError(str(err)) from None
    print(report.table())
    if args.out is not None:
        args.out.write_text(report.to_csv(), encoding="utf-8")
        print(f"per-measurement errors written to {args.out}")
    return 0 if report.passed else 1
