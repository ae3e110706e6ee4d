"""Commissioning validation as the paper's Tables 1–3: measured offsets against the truth, per axis.

Ground truth comes from robot teaching or from the tooling's read-outs (CSV, one row per
measurement, in the recipe's robot convention); the measured offsets come from the station (its CSV
export or any CSV with the same columns). Rows are matched by a key column, never by position, so a
missing measurement is reported instead of shifting its neighbours.

Errors are taken where the robot uses the result, at the recipe's grasp frame: with
``T_rf_from_pf = offset · T_rf_from_pf0`` for both truth and measurement and
``G = T_rf_from_pf · T_pf_from_grasp``,

    translation error (mm)  = t(G_meas) − t(G_true)               in robot base axes X Y Z
    rotation error (deg)    = rotvec(R(G_meas) · R(G_true)ᵀ)       about the base axes X Y Z

For small angles the rotation components are the α β γ of the paper's tables (rotations about X, Y
and Z); unlike differences of Euler angles they do not depend on the robot's convention. The sign
is measured − true (the paper writes true − computed; only the sign of the mean changes).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, compose, from_robot, matrix_to_rotvec

KEY_COLUMNS = ("index", "key", "trigger_id", "part_id", "id")


class ValidationError(ValueError):
    """Validation input cannot be used; the message names the file, the row and the value."""


def _column(fieldnames: Sequence[str], label: str, position: int) -> str | None:
    """The CSV column of ``label`` (``X``, ``offset_X``, any case) or ``o<position>`` (export)."""
    wanted = {label.lower(), f"offset_{label}".lower(), f"offset.{label}".lower(), f"o{position}"}
    for name in fieldnames:
        if name.strip().lower() in wanted:
            return name
    return None


def read_offsets_csv(
    source: str | Path | io.TextIOBase, recipe: RecipeConfig, key: str | None = None
) -> dict[str, Array]:
    """Offsets per key from a CSV in the recipe's robot convention, as 4x4 base-frame transforms.

    ``key`` names the column that identifies a measurement; by default the first of
    :data:`KEY_COLUMNS` present. Columns are the convention's labels (``X Y Z W P R`` for FANUC,
    optionally prefixed ``offset_``) or ``o1 … o6`` in that order, as the station's measurement
    export (``GET /api/v1/measurements/export``) writes them; other columns are ignored. Rows
    without an offset (NOK measurements in an export) are skipped.
    """
    if isinstance(source, (str, Path)):
        name = str(source)
        try:
            text = Path(source).read_text(encoding="utf-8-sig")
        except OSError as err:
            raise ValidationError(f"{name}: cannot read: {err.strerror}") from None
    else:
        name = getattr(source, "name", "<stream>")
        text = source.read()
    reader = csv.DictReader(io.StringIO(text))
    fields = list(reader.fieldnames or [])
    if not fields:
        raise ValidationError(f"{name}: empty file, expected a header row")
    conv = recipe.robot_convention
    if key is None:
        key = next((c for c in fields if c.strip().lower() in KEY_COLUMNS), None)
        if key is None:
            raise ValidationError(
                f"{name}: no key column; expected one of {list(KEY_COLUMNS)}, got {fields}"
            )
    elif key not in fields:
        raise ValidationError(f"{name}: no column {key!r}; columns are {fields}")
    cols = {lab: _column(fields, lab, i + 1) for i, lab in enumerate(conv.labels)}
    missing = [lab for lab, c in cols.items() if c is None]
    if missing:
        raise ValidationError(
            f"{name}: a {conv.value} offset needs columns {list(conv.labels)}; missing {missing} "
            f"(columns: {fields})"
        )
    out: dict[str, Array] = {}
    for line, row in enumerate(reader, start=2):
        k = (row.get(key) or "").strip()
        if not k:
            raise ValidationError(f"{name}: line {line}: empty {key!r}")
        if k in out:
            raise ValidationError(f"{name}: line {line}: {key} {k!r} appears twice")
        if all(not (row.get(c) or "").strip() for c in cols.values() if c):
            continue  # a NOK measurement of an export: no offset to compare
        values = []
        for c in cols.values():
            raw = (row.get(c) or "").strip() if c else ""
            try:
                v = float(raw)
            except ValueError:
                raise ValidationError(
                    f"{name}: line {line}: column {c!r} is not a number (value: {raw!r})"
                ) from None
            if not math.isfinite(v):
                raise ValidationError(f"{name}: line {line}: column {c!r} is {raw!r}")
            values.append(v)
        try:
            out[k] = from_robot(values, conv)
        except ValueError as err:
            raise ValidationError(f"{name}: line {line}: {err}") from None
    if not out:
        raise ValidationError(f"{name}: no rows")
    return out


class TruthWriter:
    """A truth file as :func:`read_offsets_csv` reads it, written a row per trigger as it comes
    (a rehearsal on simulated cameras knows the truth): keys ``trigger_id`` and ``part_id``, the
    true offset in the recipe's convention (``X Y Z W P R`` for FANUC), then what the station
    answered beside it (``measured_X`` …, empty for a NOK; ``result``; the errors at the grasp),
    which :func:`read_offsets_csv` ignores. Each row is flushed, so a run stopped with Ctrl-C
    leaves every trigger answered so far."""

    def __init__(self, path: Path, recipe: RecipeConfig) -> None:
        self.path = Path(path)
        self.labels = list(recipe.robot_convention.labels)
        self._file: TextIO = self.path.open("w", newline="", encoding="utf-8")
        self._csv = csv.writer(self._file, lineterminator="\n")
        self._csv.writerow(["trigger_id", "part_id", *self.labels,
                            *(f"measured_{lab}" for lab in self.labels), "result",
                            "rot_err_deg", "trans_err_mm"])
        self._file.flush()

    def add(self, trigger_id: int, part_id: str, true_offset: Sequence[float] | Array,
            measured_offset: Sequence[float] | Array | None, result: str,
            errors: tuple[float, float] | None) -> None:
        measured = [f"{v:.6f}" for v in measured_offset] if measured_offset is not None else [
            ""] * len(self.labels)
        err = [f"{errors[0]:.6f}", f"{errors[1]:.6f}"] if errors is not None else ["", ""]
        self._csv.writerow([trigger_id, part_id, *(f"{v:.6f}" for v in true_offset),
                            *measured, result, *err])
        self._file.flush()

    def close(self) -> None:
        self._file.close()


@dataclass(frozen=True)
class AxisStats:
    """Per-axis statistics of errors ``[N, 3]``."""

    mean: Array
    std: Array  # sample std (ddof = 1), as the paper's ±
    rms: Array
    max_abs: Array

    @classmethod
    def of(cls, errors: Array) -> AxisStats:
        e = np.asarray(errors, dtype=float).reshape(-1, 3)
        ddof = 1 if len(e) > 1 else 0
        return cls(
            mean=e.mean(axis=0), std=e.std(axis=0, ddof=ddof),
            rms=np.sqrt(np.mean(e**2, axis=0)), max_abs=np.abs(e).max(axis=0),
        )


@dataclass(frozen=True)
class ValidationRow:
    key: str
    rotation_deg: Array  # [3] about RF X, Y, Z
    translation_mm: Array  # [3] along RF X, Y, Z

    @property
    def angle_deg(self) -> float:
        return float(np.linalg.norm(self.rotation_deg))

    @property
    def distance_mm(self) -> float:
        return float(np.linalg.norm(self.translation_mm))


@dataclass(frozen=True)
class ValidationReport:
    """Per-measurement errors and their statistics; ``passed`` against the recipe's tolerances.

    As in the paper (Section 3.2: RMS 0.123° and 0.731 mm against the 0.2° and 1.0 mm a grasp
    needs), the RMS of the total errors is held against the recipe's tolerances; single rows
    beyond them are flagged in the table.
    """

    recipe: str
    rows: tuple[ValidationRow, ...]
    rotation: AxisStats
    translation: AxisStats
    angle_rms_deg: float  # RMS of the total rotation error (the paper's dR)
    angle_std_deg: float
    distance_rms_mm: float  # RMS of the total translation error (the paper's dT)
    distance_std_mm: float
    tolerance_deg: float
    tolerance_mm: float
    missing_measurements: tuple[str, ...]  # keys with truth but no measurement
    unmatched_measurements: tuple[str, ...]  # keys measured but without truth

    @property
    def passed(self) -> bool:
        """Total RMS errors within the tolerances, and no measurement missing."""
        return (
            not self.missing_measurements
            and self.angle_rms_deg <= self.tolerance_deg
            and self.distance_rms_mm <= self.tolerance_mm
        )

    def table(self) -> str:
        """The report as text, laid out like the paper's tables."""
        lines = [
            f"commissioning validation, recipe {self.recipe!r}: {len(self.rows)} measurements, "
            "errors at the grasp frame (measured - true, robot base axes)",
            f"{'index':>12} | {'rotation error (deg)':^26} | {'translation error (mm)':^26} |"
            f" {'|dR|':>6} {'|dT|':>6}",
            f"{'':>12} | {'a':>8}{'b':>9}{'g':>9} | {'X':>8}{'Y':>9}{'Z':>9} |",
        ]
        for r in self.rows:
            a, b, g = r.rotation_deg
            x, y, z = r.translation_mm
            flag = "" if r.angle_deg <= self.tolerance_deg and r.distance_mm <= self.tolerance_mm \
                else "  beyond tolerance"
            lines.append(
                f"{r.key:>12} | {a:8.3f} {b:8.3f} {g:8.3f} | {x:8.3f} {y:8.3f} {z:8.3f} |"
                f" {r.angle_deg:6.3f} {r.distance_mm:6.3f}{flag}"
            )
        for label, fn in (("mean", "mean"), ("std", "std"), ("RMS", "rms"), ("max |e|", "max_abs")):
            ro, tr = getattr(self.rotation, fn), getattr(self.translation, fn)
            lines.append(
                f"{label:>12} | {ro[0]:8.3f} {ro[1]:8.3f} {ro[2]:8.3f} |"
                f" {tr[0]:8.3f} {tr[1]:8.3f} {tr[2]:8.3f} |"
            )
        lines.append(
            f"total: RMS {self.angle_rms_deg:.3f} deg and {self.distance_rms_mm:.3f} mm, "
            f"std {self.angle_std_deg:.3f} deg and {self.distance_std_mm:.3f} mm "
            f"(tolerance {self.tolerance_deg:g} deg, {self.tolerance_mm:g} mm)"
        )
        if self.missing_measurements:
            lines.append(f"MISSING measurements for: {', '.join(self.missing_measurements)}")
        if self.unmatched_measurements:
            lines.append(f"measurements without truth (ignored): "
                         f"{', '.join(self.unmatched_measurements)}")
        lines.append("PASSED" if self.passed else "FAILED")
        return "\n".join(lines)

    def to_csv(self) -> str:
        """One row per measurement with its errors (for the commissioning file)."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["index", "rot_x_deg", "rot_y_deg", "rot_z_deg", "x_mm", "y_mm", "z_mm",
                    "angle_deg", "distance_mm"])
        for r in self.rows:
            w.writerow([r.key, *(f"{v:.4f}" for v in r.rotation_deg),
                        *(f"{v:.4f}" for v in r.translation_mm),
                        f"{r.angle_deg:.4f}", f"{r.distance_mm:.4f}"])
        return buf.getvalue()


def grasp_error(
    offset_true: Array, offset_meas: Array, recipe: RecipeConfig
) -> tuple[Array, Array]:
    """(rotation error deg [3], translation error mm [3]) at the grasp frame, in RF axes."""
    T_pf0 = recipe.T_rf_from_pf0.matrix
    T_grasp = recipe.T_pf_from_grasp.matrix
    G_true = compose(offset_true, T_pf0, T_grasp)
    G_meas = compose(offset_meas, T_pf0, T_grasp)
    rot = np.degrees(matrix_to_rotvec(G_meas[:3, :3] @ G_true[:3, :3].T))
    return rot, G_meas[:3, 3] - G_true[:3, 3]


def _natural(key: str) -> tuple[int, float | str]:
    try:
        return (0, float(key))
    except ValueError:
        return (1, key)


def validate_offsets(
    truth: Mapping[str, Array], measured: Mapping[str, Array], recipe: RecipeConfig
) -> ValidationReport:
    """Compare measured offsets with ground truth, matched by key."""
    keys = sorted((k for k in truth if k in measured), key=_natural)
    if not keys:
        raise ValidationError(
            f"no measurement matches the ground truth: truth keys {sorted(truth)[:5]}..., "
            f"measured keys {sorted(measured)[:5]}..."
        )
    rows = []
    for k in keys:
        rot, trans = grasp_error(truth[k], measured[k], recipe)
        rows.append(ValidationRow(key=k, rotation_deg=rot, translation_mm=trans))
    R = np.array([r.rotation_deg for r in rows])
    T = np.array([r.translation_mm for r in rows])
    angles = np.linalg.norm(R, axis=1)
    dists = np.linalg.norm(T, axis=1)
    ddof = 1 if len(rows) > 1 else 0
    return ValidationReport(
        recipe=recipe.name,
        rows=tuple(rows),
        rotation=AxisStats.of(R),
        translation=AxisStats.of(T),
        angle_rms_deg=float(np.sqrt(np.mean(angles**2))),
        angle_std_deg=float(np.std(angles, ddof=ddof)),
        distance_rms_mm=float(np.sqrt(np.mean(dists**2))),
        distance_std_mm=float(np.std(dists, ddof=ddof)),
        tolerance_deg=recipe.tolerances.rotation_deg,
        tolerance_mm=recipe.tolerances.translation_mm,
        missing_measurements=tuple(sorted((k for k in truth if k not in measured), key=_natural)),
        unmatched_measurements=tuple(sorted((k for k in measured if k not in truth), key=_natural)),
    )
