"""``mvpose replay``: re-measure archived measurements with another calibration or recipe version.

Reads the station's store (its measurement records) and image archive (the frames it kept: NOK
always, OK 1 in ``MVPOSE_IMAGES_OK_EVERY``), measures each archived trigger again through the
station's pipeline (:mod:`server.commands.offline`) with the station file given — its
calibration, or ``--calibration`` — and each record's own recipe version, or
``--recipe-version``; writes the new results side by side with the original ones. Nothing is
written to the store. Records store no actual flange poses: robot-mounted views are re-measured
at their taught poses.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
from collections.abc import Iterator
from pathlib import Path

from tqdm import tqdm

from mvpose_core.station import RecipeConfig, StationConfig
from server.cli import CliError, load_station_file
from server.commands.archived import frames_of, open_data_dir, when
from server.commands.measure import calibrated
from server.commands.offline import (
    OfflineStation,
    Outcome,
    grasp_difference,
    result_columns,
    result_values,
    summary,
)
from server.errors import NotFoundError
from server.recipes import ActiveRecipe
from server.store import Store
from server.store.schemas import MeasurementFilter, StoredMeasurement


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--station", required=True, type=Path,
                        help="station YAML file to re-measure with (its calibration: applies)")
    parser.add_argument("--calibration", type=Path,
                        help="calibration file to re-measure with instead of the station file's")
    parser.add_argument("--recipe-version", type=int,
                        help="stored recipe version to re-measure with (default: each record's)")
    parser.add_argument("--data-dir", type=Path, default=Path("var"),
                        help="the station's data folder: store and image archive (default ./var)")
    parser.add_argument("--database-url", help="store URL (default sqlite:///<data-dir>/mvpose.db)")
    parser.add_argument("--images-dir", type=Path, help="image archive (default <data-dir>/images)")
    parser.add_argument("--ids", help="measurement ids, comma-separated (default: all)")
    parser.add_argument("--since", type=when, help="triggered at or after (ISO time; UTC "
                        "unless it names its zone)")
    parser.add_argument("--until", type=when, help="triggered before (ISO time)")
    parser.add_argument("--result", choices=["OK", "NOK"], help="only OK or only NOK records")
    parser.add_argument("--out", type=Path, default=Path("replay"),
                        help="folder for replay.csv and replay.json (default ./replay)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _records(store: Store, args: argparse.Namespace) -> Iterator[StoredMeasurement]:
    if args.ids:
        try:
            ids = [int(x) for x in args.ids.split(",") if x.strip()]
        except ValueError:
            raise CliError(f"--ids: expected comma-separated integers, got {args.ids!r}") from None
        for i in ids:
            try:
                yield store.measurements.get(i)
            except NotFoundError as err:
                raise CliError(f"measurement {i}: {err}") from None
        return
    filters = MeasurementFilter(since=args.since, until=args.until, result=args.result)
    yield from store.measurements.iterate(filters)


class Replayer:
    """One offline station per recipe version, built when first needed."""

    def __init__(self, station: StationConfig, store: Store,
                 calibration: tuple[str, str] | None, recipe_version: int | None) -> None:
        self.station = station
        self.store = store
        self.calibration = calibration
        self.recipe_version = recipe_version
        self._stations: dict[tuple[str, int], OfflineStation] = {}

    def recipe(self, name: str, version: int) -> ActiveRecipe:
        number = next((i for i, r in enumerate(self.station.recipes, 1) if r.name == name), None)
        if number is None:
            raise CliError(f"recipe {name!r} of the archive is not in station "
                           f"{self.station.name!r}")
        try:
            info, content = self.store.versions.content("recipe", name, version)
        except NotFoundError as err:
            raise CliError(str(err)) from None
        cfg = RecipeConfig.model_validate({**content, "version": info.version})
        return ActiveRecipe(cfg, info.version, info.sha256, number)

    def offline(self, name: str, version: int) -> OfflineStation:
        version = self.recipe_version or version
        key = (name, version)
        if key not in self._stations:
            self._stations[key] = OfflineStation(self.station, self.recipe(name, version),
                                                 self.calibration)
        return self._stations[key]

    def close(self) -> None:
        for s in self._stations.values():
            s.close()


def write_side_by_side(out: Path, rows: list[tuple[StoredMeasurement, Outcome | None, str]],
                       recipe: RecipeConfig) -> tuple[Path, Path]:
    """``replay.csv``: per measurement the original figures (``orig_*``), the new ones under the
    plain column names (so ``mvpose validate`` reads them) and the grasp-frame difference."""
    out.mkdir(parents=True, exist_ok=True)
    labels = list(recipe.robot_convention.labels)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["key", "id", "trigger_id", "part_id", "recipe", "orig_recipe_version",
                "orig_calibration_id", "orig_result", "orig_reason_code", "orig_reason",
                *(f"orig_{c}" for c in labels), "orig_sigma_mm", "orig_sigma_deg",
                "recipe_version", "calibration_id", *result_columns(recipe),
                "diff_deg", "diff_mm", "note"])
    for m, o, note in rows:
        r = m.record
        orig_offset = list(r.offset.values) if r.offset and r.result == "OK" else [""] * len(
            labels)
        new: list[object] = ["", "", *([""] * len(result_columns(recipe)))]
        diff: list[object] = ["", ""]
        if o is not None:
            new = [o.record.recipe_version, o.record.calibration_id or "", *result_values(o)]
            if r.T_rf_from_pf is not None and o.record.T_rf_from_pf is not None:
                diff = list(grasp_difference(r.T_rf_from_pf, o.record.T_rf_from_pf, recipe))
        w.writerow([r.part_id or str(m.id), m.id, r.trigger_id, r.part_id or "", r.recipe,
                    r.recipe_version, r.calibration_id or "", r.result, r.reason_code, r.reason,
                    *orig_offset, r.uncertainty.sigma_mm if r.uncertainty else "",
                    r.uncertainty.sigma_deg if r.uncertainty else "", *new, *diff, note])
    csv_path = out / "replay.csv"
    csv_path.write_text(buf.getvalue(), encoding="utf-8")
    json_path = out / "replay.json"
    json_path.write_text(json.dumps(
        [{"id": m.id, "original": m.record.model_dump(mode="json"),
          "replayed": o.record.model_dump(mode="json") if o else None, "note": note}
         for m, o, note in rows], indent=1) + "\n", encoding="utf-8")
    return csv_path, json_path


def run(args: argparse.Namespace) -> int:
    station = load_station_file(args.station)
    station, calib = calibrated(station, args.station, args.calibration)
    store = open_data_dir(args.data_dir, args.database_url, station.name)
    images = args.images_dir or args.data_dir / "images"
    replayer = Replayer(station, store, calib, args.recipe_version)
    rows: list[tuple[StoredMeasurement, Outcome | None, str]] = []
    try:
        for m in tqdm(list(_records(store, args)), desc="replay", unit="measurement",
                      disable=args.quiet):
            r = m.record
            if not store.images.for_measurement(m.id):
                rows.append((m, None, "no archived frames"))
                continue
            offline = replayer.offline(r.recipe, r.recipe_version)
            o = offline.measure(r.part_id or str(m.id), r.trigger_id, frames_of(store, images, m),
                                triggered_at=r.triggered_at, part_id=r.part_id)
            rows.append((m, o, ""))
    finally:
        replayer.close()
        store.close()
    if not rows:
        raise CliError("no measurements match")
    recipe = station.recipe(rows[0][0].record.recipe)
    csv_path, json_path = write_side_by_side(args.out, rows, recipe)
    done = [o for _, o, _ in rows if o is not None]
    print(f"{len(rows)} measurements, {len(rows) - len(done)} without archived frames; "
          f"re-measured: {summary(done)}")
    changed = sum(1 for m, o, _ in rows if o is not None and o.record.result != m.record.result)
    print(f"{changed} changed OK/NOK; written to {csv_path} and {json_path}")
    return 0
