"""``mvpose gauge type1|type3|linearity``: a gauge capability study on stored measurements or a
file of offsets, its report (HTML and PDF) and its record in the audit trail (docs/gauge.md).

Measurements come from the station's store (``--data-dir`` or ``--database-url``, chosen by
``--part-id``, ``--since``/``--until`` or ``--ids``), from a file (``--measured``: the station's
CSV export, or what ``mvpose measure`` wrote for an image folder), or from a stored study
(``--study``: its report again). A study of stored measurements is recorded in the store.
"""

from __future__ import annotations

import argparse
import json
from datetime import UTC, datetime
from pathlib import Path

from mvpose_core.gauge import GaugeError
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import to_robot
from server.cli import CliError, load_station_file, station_recipe
from server.gauge.report import ReportHeader, table, to_html, to_pdf
from server.gauge.sources import (
    Selection,
    StudyRequest,
    build_study,
    file_samples,
    stored_samples,
)
from server.gauge.study import GaugeStudy, passed
from server.store import Store, open_store
from server.validation import ValidationError, read_offsets_csv


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("kind", choices=["type1", "type3", "linearity"],
                        help="type1: one part ≥ 25 times (Cg, Cgk); type3: n parts × r repeats "
                        "(%%GRR, ndc); linearity: bias against known displacements")
    parser.add_argument("--station", required=True, type=Path, help="station YAML file")
    parser.add_argument("--recipe", help="recipe name (default: the station's default recipe)")
    src = parser.add_argument_group("measurements (the store, a file, or a stored study)")
    src.add_argument("--data-dir", type=Path,
                     help="the station's data folder: its store is <data-dir>/mvpose.db")
    src.add_argument("--database-url", help="store URL (instead of --data-dir)")
    src.add_argument("--part-id", help="stored measurements of this part id")
    src.add_argument("--since", type=_when, help="triggered at or after (ISO time; UTC default)")
    src.add_argument("--until", type=_when, help="triggered before (ISO time)")
    src.add_argument("--ids", help="result ids (seq), comma-separated")
    src.add_argument("--measured", type=Path,
                     help="offsets from a file: the station's CSV export, or mvpose measure's "
                     "measurements.csv / .json for an image folder")
    src.add_argument("--images", type=Path,
                     help="an image folder (one sub-folder per trigger, named by its part id), "
                     "measured first as mvpose measure measures it (into <out>/measured)")
    src.add_argument("--study", type=int, help="a stored study's id: write its report again")
    parser.add_argument("--same-part", action="store_true",
                        help="type1: the selection is one part whatever its part ids say (a "
                        "rehearsal that holds the part still numbers its part ids by trigger)")
    parser.add_argument("--reference",
                        help="type1: the part's true offset in the recipe's convention, "
                        "comma-separated (e.g. X,Y,Z,W,P,R); without it no bias and no Cgk")
    parser.add_argument("--truth", type=Path,
                        help="linearity: known displacements (CSV as mvpose validate reads it, "
                        "keyed like the measurements: result id for stored ones)")
    parser.add_argument("--key", help="key column of --measured and --truth")
    parser.add_argument("--tolerance-mm", type=float,
                        help="tolerance width T of lengths (default 2 × the recipe's "
                        "translation_mm)")
    parser.add_argument("--tolerance-deg", type=float,
                        help="tolerance width T of angles (default 2 × rotation_deg)")
    parser.add_argument("--title", default="", help="a line for the report (gauge, part, why)")
    parser.add_argument("--by", default="cli", help="who made the study (stored with it)")
    parser.add_argument("--out", type=Path, default=Path("gauge"),
                        help="folder for report.html, report.pdf and study.json (default ./gauge)")


def _when(text: str) -> datetime:
    t = datetime.fromisoformat(text)
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def _floats(text: str, what: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",")]
    except ValueError:
        raise CliError(f"{what}: expected comma-separated numbers, got {text!r}") from None


def _store(args: argparse.Namespace, station_name: str) -> Store | None:
    if args.database_url is None and args.data_dir is None:
        return None
    url = args.database_url
    if url is None:
        db = args.data_dir / "mvpose.db"
        if not db.is_file():
            raise CliError(f"{args.data_dir}: no store (mvpose.db); give --data-dir or "
                           "--database-url")
        url = f"sqlite:///{db.as_posix()}"
    return open_store(url, station_name)


def run(args: argparse.Namespace) -> int:
    station = load_station_file(args.station)
    recipe = station_recipe(station, args.recipe)
    store = _store(args, station.name)
    if args.images is not None:
        if args.measured is not None:
            raise CliError("give --images or --measured, not both")
        args.measured = measure_folder(args)
    if args.measured is None and store is None:
        raise CliError("give the measurements: --data-dir / --database-url (the store), "
                       "--measured FILE or --images FOLDER")
    try:
        header = ReportHeader(station=station.name, created_at=datetime.now(UTC),
                              created_by=args.by)
        if args.study is not None:
            if store is None:
                raise CliError("--study needs the store (--data-dir or --database-url)")
            stored = store.gauge.get(args.study)
            study = GaugeStudy.from_json(stored.body)
            header = ReportHeader(station.name, stored.id, stored.created_at,
                                  stored.created_by, stored.hash)
        else:
            study = _new_study(args, recipe, store)
            if args.measured is None and store is not None:
                stored = store.gauge.add(study.to_json(), args.by)
                header = ReportHeader(station.name, stored.id, stored.created_at,
                                      stored.created_by, stored.hash)
        html_text = to_html(study, header)
        pdf_bytes = to_pdf(study, header)
    except GaugeError as err:
        raise CliError(str(err)) from None
    finally:
        if store is not None:
            store.close()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.html").write_text(html_text, encoding="utf-8")
    (args.out / "report.pdf").write_bytes(pdf_bytes)
    (args.out / "study.json").write_text(json.dumps(study.to_json(), indent=1) + "\n",
                                         encoding="utf-8")
    results = study.results()
    head, rows = table(results)
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    print("  ".join(h.rjust(w) for h, w in zip(head, widths, strict=True)))
    for row in rows:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)))
    ok = passed(results)
    recorded = f" (study {header.study_id} in the audit trail)" if header.study_id else ""
    print(f"{'PASSED' if ok else 'FAILED'}{recorded}; report in {args.out}/report.html and "
          "report.pdf")
    return 0 if ok else 1


def measure_folder(args: argparse.Namespace) -> Path:
    """Measure ``args.images`` as ``mvpose measure`` does; the records' JSON it wrote."""
    from server.commands import measure

    out = args.out / "measured"
    # through measure's own parser, so its options' defaults come with it
    parser = argparse.ArgumentParser(prog="mvpose measure")
    measure.add_arguments(parser)
    argv = ["--station", str(args.station), "--images", str(args.images), "--out", str(out),
            "--quiet", *(["--recipe", args.recipe] if args.recipe else [])]
    measure.run(parser.parse_args(argv))
    return out / "measurements.json"


def _new_study(args: argparse.Namespace, recipe: RecipeConfig,
               store: Store | None) -> GaugeStudy:
    truth: dict[str, list[float]] = {}
    if args.truth is not None:
        try:
            offsets = read_offsets_csv(args.truth, recipe, args.key)
        except ValidationError as err:
            raise CliError(str(err)) from None
        truth = {k: [float(v) for v in to_robot(T, recipe.robot_convention)]
                 for k, T in offsets.items()}
    if args.kind == "linearity" and not truth:
        raise CliError("a linearity study needs --truth (the known displacements)")
    request = StudyRequest(
        kind=args.kind,
        reference=_floats(args.reference, "--reference") if args.reference else None,
        tolerance_mm=args.tolerance_mm, tolerance_deg=args.tolerance_deg, truth=truth,
        title=args.title, same_part=args.same_part,
    )
    if args.measured is not None:
        samples = file_samples(args.measured, recipe, args.key)
        source: dict[str, object] = {"file": str(args.measured)}
        if args.images is not None:
            source = {"images": str(args.images)}
    elif store is not None:
        ids = tuple(int(x) for x in _floats(args.ids, "--ids")) if args.ids else ()
        sel = Selection(part_id=args.part_id, since=args.since, until=args.until,
                        result_ids=ids)
        samples = stored_samples(store, recipe, sel)
        source = sel.describe()
    else:
        raise CliError("give the measurements: the store or --measured FILE")
    return build_study(request, samples, recipe, source)
