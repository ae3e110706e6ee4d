"""Where a gauge study's measurements come from: the store (by part id, time window, recipe or
result ids), or a file of offsets (the station's CSV export, or what ``mvpose measure`` wrote
for an image folder), and the study built from them (the CLI and REST share this module)."""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from mvpose_core.gauge import GaugeError
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, from_robot
from server.gauge.study import (
    GaugeStudy,
    Kind,
    Tolerances,
    linearity_study,
    type1_study,
    type3_study,
)
from server.store import Store
from server.store.schemas import MeasurementFilter
from server.validation import ValidationError, read_offsets_csv


@dataclass(frozen=True)
class Sample:
    """One OK measurement: its key (the result id for stored ones), part id and offset."""

    key: str
    part_id: str | None
    offset: Array  # 4x4, robot base frame
    seq: int | None = None
    hash: str | None = None


@dataclass(frozen=True)
class Selection:
    """Stored measurements to study; every field optional (all OK records of the recipe)."""

    part_id: str | None = None
    since: datetime | None = None
    until: datetime | None = None
    result_ids: tuple[int, ...] = ()

    def describe(self) -> dict[str, Any]:
        return {"part_id": self.part_id,
                "since": self.since.isoformat() if self.since else None,
                "until": self.until.isoformat() if self.until else None,
                "result_ids": list(self.result_ids) or None}


def stored_samples(store: Store, recipe: RecipeConfig, sel: Selection) -> list[Sample]:
    """The selection's OK records of ``recipe``, oldest first."""
    filters = MeasurementFilter(since=sel.since, until=sel.until, part_id=sel.part_id,
                                recipe=recipe.name, result="OK")
    wanted = set(sel.result_ids)
    out = []
    for s in store.measurements.iterate_summaries(filters):
        if wanted and s.seq not in wanted:
            continue
        if s.offset is None:
            continue
        if s.offset.convention != recipe.robot_convention:
            raise GaugeError(f"result {s.seq}: offset in {s.offset.convention.value}, the "
                             f"recipe uses {recipe.robot_convention.value}")
        out.append(Sample(str(s.seq), s.part_id, from_robot(s.offset.values,
                                                            recipe.robot_convention),
                          s.seq, s.hash))
    if wanted and len(out) != len(wanted):
        missing = sorted(wanted - {s.seq for s in out})
        raise GaugeError(f"result ids {missing} are not OK records of recipe {recipe.name!r}")
    return out


def file_samples(path: Path, recipe: RecipeConfig, key: str | None = None) -> list[Sample]:
    """Offsets from a CSV (the export, or ``mvpose measure``'s measurements.csv) or records
    JSON (``mvpose measure``'s measurements.json), in the file's order."""
    from server.commands.validate import records_json_as_csv

    try:
        if path.suffix.lower() == ".json":
            text = records_json_as_csv(path, recipe).getvalue()
        else:
            text = path.read_text(encoding="utf-8-sig")
    except OSError as err:
        raise GaugeError(f"{path}: cannot read: {err.strerror}") from None
    except ValidationError as err:
        raise GaugeError(str(err)) from None
    rows = list(csv.DictReader(io.StringIO(text)))
    fields = list(rows[0]) if rows else []
    key = key or next((c for c in ("key", "trigger_id", "id", "index") if c in fields), None)
    if key is None:
        raise GaugeError(f"{path}: no key column (key, trigger_id, id or index); columns "
                         f"{fields}")
    buf = io.StringIO(text)
    buf.name = str(path)
    try:
        offsets = read_offsets_csv(buf, recipe, key)
    except ValidationError as err:
        raise GaugeError(str(err)) from None
    parts = {(r.get(key) or "").strip(): (r.get("part_id") or "").strip() or None for r in rows}
    return [Sample(k, parts.get(k), T) for k, T in offsets.items()]


@dataclass(frozen=True)
class StudyRequest:
    """What a study is asked for, apart from its measurements."""

    kind: Kind
    reference: list[float] | None = None  # type 1: the part's true offset (recipe convention)
    tolerance_mm: float | None = None  # full widths; default 2 × the recipe's tolerances
    tolerance_deg: float | None = None
    truth: dict[str, list[float]] = field(default_factory=dict)  # linearity: key -> offset
    title: str = ""
    same_part: bool = False  # type 1: one part whatever the records' part ids say


def build_study(request: StudyRequest, samples: list[Sample], recipe: RecipeConfig,
                source: dict[str, Any]) -> GaugeStudy:
    """The study of ``samples`` (raises GaugeError naming what does not fit)."""
    tol = Tolerances.of(recipe, request.tolerance_mm, request.tolerance_deg)
    if not samples:
        raise GaugeError(f"no OK measurement of recipe {recipe.name!r} matches the selection "
                         f"{ {k: v for k, v in source.items() if v} }")
    records = [{"seq": s.seq, "hash": s.hash} for s in samples if s.seq is not None]
    src = {**source, "tolerance_mm": tol.mm, "tolerance_deg": tol.deg}
    conv = recipe.robot_convention
    if request.kind == "type1":
        parts = sorted({s.part_id for s in samples if s.part_id})
        if request.same_part:
            src["same_part"] = True
        elif len(parts) > 1:
            raise GaugeError(f"a type-1 study measures one part; the selection has parts "
                             f"{parts[:5]}{'…' if len(parts) > 5 else ''} (choose one part "
                             "id, or say it is one part: --same-part)")
        ref = None
        if request.reference is not None:
            try:
                ref = from_robot(request.reference, conv)
            except ValueError as err:
                raise GaugeError(f"reference: {err}") from None
            src["reference"] = list(request.reference)
        return type1_study([s.offset for s in samples], recipe, tol, ref, src, records,
                           request.title)
    if request.kind == "type3":
        by_part: dict[str, list[Array]] = {}
        for s in samples:
            if not s.part_id:
                raise GaugeError(f"measurement {s.key} has no part id; a type-3 study groups "
                                 "its measurements by part id")
            by_part.setdefault(s.part_id, []).append(s.offset)
        return type3_study(by_part, recipe, tol, src, records, request.title)
    if not request.truth:
        raise GaugeError("a linearity study needs the known displacements (truth offsets)")
    truth = {}
    for k, values in request.truth.items():
        try:
            truth[k] = from_robot(values, conv)
        except ValueError as err:
            raise GaugeError(f"truth {k!r}: {err}") from None
    measured = {s.key: s.offset for s in samples}
    study = linearity_study(truth, measured, recipe, src, request.title)
    keys = set(study.source["keys"])
    used = [{"seq": s.seq, "hash": s.hash} for s in samples if s.seq is not None and s.key in keys]
    return GaugeStudy(study.kind, study.recipe, study.source, study.characteristics, used,
                      study.title)
