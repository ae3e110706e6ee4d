"""``mvpose measure``: the station's measurement of saved images, offline, without a deadline.

Layout of ``--images``: one folder per trigger (its name is the measurement's key and part id);
in it one image per camera named by camera id (``top_left.png``), or, when the recipe measures in
several views (robot-mounted rigs), one subfolder per view (``v1/``, ``v2/``; ``1/`` also works)
holding the cameras of that view. A view folder may hold ``flange.yaml``, the robot's actual
flange pose at that view in any station-file pose form (``{convention: fanuc, values: [...]}``,
``{matrix: ...}``, ``{xyz, wpr}``); without it the taught pose is used. A camera's missing or
unreadable image fails that camera of that trigger alone, as a camera that gave no frame.

``--from-archive DATA_DIR`` reads the station's own data folder instead: the stored records of
the recipe (selected by ``--result-ids`` and ``--since``/``--until``) whose frames the image
archive kept, each measured from those frames at its record's trigger id, part id and trigger
time, keyed by its result id. Records without archived frames are counted and skipped.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import yaml
from tqdm import tqdm

from drivers.cameras import DriverError, Frame
from drivers.cameras.files import IMAGE_SUFFIXES, read_image
from mvpose_core.calibration import files as calibration_files
from mvpose_core.station import Pose, RecipeConfig, StationConfig
from mvpose_core.transforms import Array
from server.cli import CliError, load_station_file, station_recipe
from server.commands.archived import frames_of, open_data_dir, result_id_ranges, when
from server.commands.offline import (
    OfflineStation,
    Outcome,
    active_recipe,
    summary,
    write_results,
)
from server.store.schemas import MeasurementFilter


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--station", required=True, type=Path, help="station YAML file")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", type=Path,
                        help="folder with one subfolder per trigger (see docs/operations.md)")
    source.add_argument("--from-archive", type=Path, metavar="DATA_DIR",
                        help="a station's data folder: its stored records' archived frames")
    parser.add_argument("--database-url",
                        help="--from-archive: store URL (default sqlite:///<DATA_DIR>/mvpose.db)")
    parser.add_argument("--images-dir", type=Path,
                        help="--from-archive: image archive (default <DATA_DIR>/images)")
    parser.add_argument("--result-ids",
                        help="--from-archive: result ids or ranges, e.g. 3,7,12-40 (default: all)")
    parser.add_argument("--since", type=when,
                        help="--from-archive: triggered at or after (ISO time; UTC unless it "
                        "names its zone)")
    parser.add_argument("--until", type=when, help="--from-archive: triggered before (ISO time)")
    parser.add_argument("--recipe", help="recipe name (default: the station's default recipe)")
    parser.add_argument("--calibration", type=Path,
                        help="calibration file to measure with (default: the station file's)")
    parser.add_argument("--out", type=Path,
                        help="folder for measurements.csv and .json (default: <images>/measured; "
                        "with --from-archive ./measured)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def calibrated(station: StationConfig, station_path: Path,
               calibration: Path | None) -> tuple[StationConfig, tuple[str, str] | None]:
    """The station with its own calibration file applied, or with ``calibration`` instead."""
    try:
        if calibration is None:
            st, ref = calibration_files.calibrated_station(station, station_path)
            return st, (ref.id, ref.sha256) if ref else None
        calib = calibration_files.load_calibration(calibration)
        return calibration_files.apply_calibration(station, calib), (calib.id, calib.sha256)
    except calibration_files.CalibrationFileError as err:
        raise CliError(str(err)) from None


def _natural(name: str) -> list[object]:
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def trigger_folders(images: Path) -> list[Path]:
    """The trigger folders of ``images`` in natural name order."""
    if not images.is_dir():
        raise CliError(f"{images}: no such folder")
    folders = sorted((p for p in images.iterdir() if p.is_dir()), key=lambda p: _natural(p.name))
    if not folders:
        raise CliError(f"{images}: no trigger folders (one subfolder per trigger, each holding "
                       "an image per camera named by camera id)")
    return folders


def view_folder(trigger: Path, view: int, several: bool) -> Path | None:
    for name in (f"v{view}", str(view)):
        if (trigger / name).is_dir():
            return trigger / name
    return None if several else trigger


def read_trigger(
    trigger: Path, views: dict[int, list[str]], several: bool
) -> tuple[dict[tuple[int, str], Frame | DriverError], dict[int, Array]]:
    """Every camera's frame (or the error naming the missing or bad file) and the flange poses
    given for the views of one trigger folder."""
    frames: dict[tuple[int, str], Frame | DriverError] = {}
    flanges: dict[int, Array] = {}
    for view, cams in views.items():
        folder = view_folder(trigger, view, several)
        for k, cid in enumerate(cams):
            if folder is None:
                frames[(view, cid)] = DriverError(
                    f"camera {cid!r}: no view folder v{view} in {str(trigger)!r}")
                continue
            files = [f for f in (folder / f"{cid}{s}" for s in IMAGE_SUFFIXES) if f.is_file()]
            if not files:
                frames[(view, cid)] = DriverError(
                    f"camera {cid!r}: no image {cid}.png (or {', '.join(IMAGE_SUFFIXES[1:])}) in "
                    f"{str(folder)!r}")
                continue
            try:
                frames[(view, cid)] = Frame(cid, read_image(files[0], cid), k, float("nan"),
                                            float("nan"))
            except DriverError as err:
                frames[(view, cid)] = err
        pose_file = folder / "flange.yaml" if folder is not None else None
        if pose_file is not None and pose_file.is_file():
            try:
                flanges[view] = Pose.model_validate(yaml.safe_load(pose_file.read_text())).matrix
            except (ValueError, yaml.YAMLError) as err:
                raise CliError(f"{pose_file}: not a pose: {err}") from None
    return frames, flanges


def run(args: argparse.Namespace) -> int:
    if args.images is not None:
        archive_only = [f"--{k.replace('_', '-')}" for k in
                        ("database_url", "images_dir", "result_ids", "since", "until")
                        if getattr(args, k) is not None]
        if archive_only:
            raise CliError(f"{', '.join(archive_only)}: only with --from-archive")
    station = load_station_file(args.station)
    station, calib = calibrated(station, args.station, args.calibration)
    recipe = station_recipe(station, args.recipe)
    offline = OfflineStation(station, active_recipe(station, recipe), calib)
    try:
        if args.images is not None:
            outcomes = _measure_folders(args, station, recipe, offline)
            out = args.out or args.images / "measured"
        else:
            outcomes = _measure_archive(args, station, recipe, offline)
            out = args.out or Path("measured")
    finally:
        offline.close()
    csv_path, json_path = write_results(out, recipe, outcomes)
    print(summary(outcomes))
    print(f"records written to {csv_path} and {json_path}")
    return 0


def _measure_folders(args: argparse.Namespace, station: StationConfig, recipe: RecipeConfig,
                     offline: OfflineStation) -> list[Outcome]:
    folders = trigger_folders(args.images)
    views = {v: [cid for cid in station.view_camera_ids(v)
                 if any(s.view == v and s.camera == cid for s in recipe.sightings)]
             for v in offline.views()}
    several = len(views) > 1 or station.robot_mounted
    outcomes = []
    for n, folder in enumerate(tqdm(folders, desc="measure", unit="trigger",
                                    disable=args.quiet), start=1):
        if len(folder.name) > 64:
            raise CliError(f"{folder}: a trigger folder's name is its part id, at most 64 "
                           f"characters (got {len(folder.name)})")
        frames, flanges = read_trigger(folder, views, several)
        outcomes.append(offline.measure(folder.name, n, frames, flanges or None))
    return outcomes


def _measure_archive(args: argparse.Namespace, station: StationConfig, recipe: RecipeConfig,
                     offline: OfflineStation) -> list[Outcome]:
    """The recipe's stored records with archived frames, measured from those frames. Records
    store no actual flange poses: robot-mounted views are measured at their taught poses."""
    data: Path = args.from_archive
    if not data.is_dir():
        raise CliError(f"{data}: no such folder (the station's data folder, MVPOSE_DATA_DIR)")
    ranges = result_id_ranges(args.result_ids) if args.result_ids else None
    images = args.images_dir or data / "images"
    store = open_data_dir(data, args.database_url, station.name)
    outcomes = []
    try:
        chosen = [m for m in store.measurements.iterate(
                      MeasurementFilter(since=args.since, until=args.until, recipe=recipe.name))
                  if ranges is None or any(lo <= m.seq <= hi for lo, hi in ranges)]
        archived = [m for m in chosen if store.images.for_measurement(m.id)]
        if not archived:
            raise CliError(f"{data}: no stored record of recipe {recipe.name!r} with archived "
                           f"frames matches ({len(chosen)} match without frames)")
        for m in tqdm(archived, desc="measure", unit="trigger", disable=args.quiet):
            r = m.record
            outcomes.append(offline.measure(str(m.seq), r.trigger_id, frames_of(store, images, m),
                                            triggered_at=r.triggered_at,
                                            part_id=r.part_id or ""))
    finally:
        store.close()
    if len(chosen) > len(archived):
        print(f"{len(chosen) - len(archived)} of {len(chosen)} matching records have no "
              "archived frames (skipped)")
    return outcomes
