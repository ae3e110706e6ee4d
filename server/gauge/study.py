"""A gauge study of a station: measured offsets turned into characteristics, the study computed
by ``mvpose_core.gauge``, and the study as the JSON body the audit trail stores (docs/gauge.md).

Characteristics are the offset's axes in the recipe's robot convention (FANUC, YASKAWA, KUKA:
X Y Z in mm and the convention's three angles in deg; ABB and UR: X Y Z in mm and the rotation
vector's components in deg) and the grasp point's displacement along the robot base axes X Y Z
(mm), as ``mvpose validate`` computes it (:func:`server.validation.grasp_error`); a type-1 study
with a reference adds the grasp point's distance from its reference position (``grasp |dT|``).

A tolerance is a full width T: by default ± the recipe's tolerance (``translation_mm`` for
lengths, ``rotation_deg`` for angles), so T = 2 × the recipe's value.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any, Literal

import numpy as np

from mvpose_core.gauge import (
    GaugeError,
    LinearityResult,
    Type1Result,
    Type3Result,
    linearity,
    type1,
    type3,
)
from mvpose_core.station import RecipeConfig
from mvpose_core.transforms import Array, RobotConvention, matrix_to_rotvec, to_robot
from server.validation import grasp_error

Kind = Literal["type1", "type3", "linearity"]
KINDS: tuple[Kind, ...] = ("type1", "type3", "linearity")
GRASP = ("grasp X", "grasp Y", "grasp Z")
DISTANCE = "grasp |dT|"


@dataclass(frozen=True)
class Tolerances:
    """Full tolerance widths T for lengths (mm) and angles (deg)."""

    mm: float
    deg: float

    @classmethod
    def of(cls, recipe: RecipeConfig, mm: float | None = None,
           deg: float | None = None) -> Tolerances:
        tol = recipe.tolerances
        return cls(mm=mm if mm is not None else 2.0 * tol.translation_mm,
                   deg=deg if deg is not None else 2.0 * tol.rotation_deg)

    def width(self, unit: str) -> float:
        return self.mm if unit == "mm" else self.deg


def axis_names(recipe: RecipeConfig) -> tuple[list[str], list[str]]:
    """(names, units) of the offset's axes as the study shows them."""
    conv = recipe.robot_convention
    if conv in (RobotConvention.ABB, RobotConvention.UR):
        return ["X", "Y", "Z", "Rx", "Ry", "Rz"], ["mm"] * 3 + ["deg"] * 3
    return list(conv.labels), ["mm"] * 3 + ["deg"] * 3


def axis_values(T: Array, recipe: RecipeConfig) -> Array:
    """The offset's six axis values (mm, deg) as :func:`axis_names` names them."""
    conv = recipe.robot_convention
    if conv in (RobotConvention.ABB, RobotConvention.UR):
        return np.array([*T[:3, 3], *np.degrees(matrix_to_rotvec(T[:3, :3]))])
    return to_robot(T, conv)


def grasp_displacement(T: Array, recipe: RecipeConfig) -> Array:
    """Where the offset moves the grasp point from its taught position (mm, robot base axes)."""
    return grasp_error(np.eye(4), T, recipe)[1]


def _characteristics(offsets: Sequence[Array], recipe: RecipeConfig) -> list[tuple[str, str,
                                                                                     Array]]:
    names, units = axis_names(recipe)
    axes = np.array([axis_values(T, recipe) for T in offsets]).reshape(-1, 6)
    grasp = np.array([grasp_displacement(T, recipe) for T in offsets]).reshape(-1, 3)
    out = [(n, u, axes[:, i]) for i, (n, u) in enumerate(zip(names, units, strict=True))]
    out += [(n, "mm", grasp[:, i]) for i, n in enumerate(GRASP)]
    return out


@dataclass(frozen=True)
class Characteristic:
    """One characteristic's data as the study stores it; ``compute`` gives its result."""

    name: str
    unit: str
    values: list[float] | list[list[float]]  # type 3: [part][repeat]; linearity: the readings
    tolerance: float | None
    reference: float | list[float] | None  # type 1: xm; linearity: one per reading
    parts: list[str] | None = None


@dataclass(frozen=True)
class GaugeStudy:
    """A study's inputs: what was measured, how it was chosen, and the limits it is held to."""

    kind: Kind
    recipe: str
    source: dict[str, Any]  # how the measurements were chosen (store query, file, image folder)
    characteristics: list[Characteristic]
    records: list[dict[str, Any]] = field(default_factory=list)  # stored records: seq and hash
    title: str = ""

    def results(self) -> list[Type1Result | Type3Result | LinearityResult]:
        out: list[Type1Result | Type3Result | LinearityResult] = []
        for c in self.characteristics:
            if self.kind == "type1":
                ref = c.reference if isinstance(c.reference, float | int) else None
                out.append(type1(np.asarray(c.values, float), float(c.tolerance or 0.0), ref,
                                 name=c.name, unit=c.unit))
            elif self.kind == "type3":
                out.append(type3(np.asarray(c.values, float), c.tolerance, parts=c.parts,
                                 name=c.name, unit=c.unit))
            else:
                out.append(linearity(np.asarray(c.reference, float), np.asarray(c.values, float),
                                     name=c.name, unit=c.unit))
        return out

    def to_json(self) -> dict[str, Any]:
        """The body the audit trail seals: the inputs, and the figures computed from them."""
        return {
            "kind": self.kind, "recipe": self.recipe, "title": self.title, "source": self.source,
            "records": self.records,
            "characteristics": [asdict(c) for c in self.characteristics],
            "figures": [figures(r) for r in self.results()],
            "passed": passed(self.results()),
        }

    @classmethod
    def from_json(cls, body: dict[str, Any]) -> GaugeStudy:
        return cls(
            kind=body["kind"], recipe=body["recipe"], source=body.get("source", {}),
            characteristics=[Characteristic(**c) for c in body["characteristics"]],
            records=body.get("records", []), title=body.get("title", ""),
        )


def figures(r: Type1Result | Type3Result | LinearityResult) -> dict[str, Any]:
    """A result's figures as JSON (no raw values: those are in the characteristic)."""
    if isinstance(r, Type1Result):
        keys = ["n", "mean", "std", "tolerance", "reference", "cg", "cgk", "bias", "t", "p",
                "bias_significant", "var_percent", "var_bias_percent"]
        extra: dict[str, Any] = {"capable": r.capable}
    elif isinstance(r, Type3Result):
        keys = ["n_parts", "repeats", "ms_parts", "ms_error", "f", "p", "ev", "pv", "tv",
                "tolerance", "spread", "grr_tv_percent", "grr_tol_percent", "ndc"]
        extra = {"grr": r.grr, "verdict": r.verdict}
    else:
        keys = ["n", "slope", "intercept", "r_squared", "s", "t_slope", "p_slope",
                "t_intercept", "p_intercept", "alpha", "levels", "level_bias"]
        extra = {"acceptable": r.acceptable}
    out = {"name": r.name, "unit": r.unit, **{k: _plain(getattr(r, k)) for k in keys}, **extra}
    return out


def _plain(v: Any) -> Any:
    if isinstance(v, float) and not np.isfinite(v):
        return None  # canonical JSON has no NaN or infinity
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    return v


def passed(results: Sequence[Type1Result | Type3Result | LinearityResult]) -> bool:
    """Every characteristic meets its limit (Cg, Cgk ≥ 1.33; %GRR ≤ 30 % and ndc ≥ 5;
    linearity: slope and intercept not significant)."""
    ok = []
    for r in results:
        if isinstance(r, Type1Result):
            ok.append(r.capable)
        elif isinstance(r, Type3Result):
            ok.append(r.verdict != "not acceptable")
        else:
            ok.append(r.acceptable)
    return bool(ok) and all(ok)


def type1_study(offsets: Sequence[Array], recipe: RecipeConfig, tolerances: Tolerances,
                reference: Array | None, source: dict[str, Any],
                records: list[dict[str, Any]] | None = None, title: str = "") -> GaugeStudy:
    """A type-1 study of one part measured again and again; ``reference`` is its true offset
    (4x4), or None when it is not known (no bias, no Cgk)."""
    if len(offsets) == 0:
        raise GaugeError("a type-1 study needs measurements; the selection has no OK record")
    chars = []
    ref_values = None if reference is None else _characteristics([reference], recipe)
    for i, (name, unit, values) in enumerate(_characteristics(offsets, recipe)):
        ref = None if ref_values is None else float(ref_values[i][2][0])
        chars.append(Characteristic(name, unit, [float(v) for v in values],
                                    tolerances.width(unit), ref))
    if reference is not None:
        dist = [float(np.linalg.norm(grasp_error(reference, T, recipe)[1])) for T in offsets]
        chars.append(Characteristic(DISTANCE, "mm", dist, tolerances.mm, 0.0))
    return GaugeStudy("type1", recipe.name, source, chars, records or [], title)


def type3_study(offsets_by_part: Mapping[str, Sequence[Array]], recipe: RecipeConfig,
                tolerances: Tolerances, source: dict[str, Any],
                records: list[dict[str, Any]] | None = None, title: str = "") -> GaugeStudy:
    """A type-3 study: every part measured the same number of times."""
    counts = {p: len(v) for p, v in offsets_by_part.items()}
    if len(counts) < 2:
        raise GaugeError(f"a type-3 study needs 2 or more parts, the selection has "
                         f"{len(counts)} ({sorted(counts)})")
    if len(set(counts.values())) != 1:
        raise GaugeError(f"a type-3 study needs the same number of repeats of every part; "
                         f"the selection has {counts}")
    parts = sorted(counts)
    per_part = [_characteristics(offsets_by_part[p], recipe) for p in parts]
    chars = []
    for i, (name, unit, _) in enumerate(per_part[0]):
        table = [[float(v) for v in pp[i][2]] for pp in per_part]
        chars.append(Characteristic(name, unit, table, tolerances.width(unit), None, parts))
    return GaugeStudy("type3", recipe.name, source, chars, records or [], title)


def linearity_study(truth: dict[str, Array], measured: dict[str, Array], recipe: RecipeConfig,
                    source: dict[str, Any], title: str = "") -> GaugeStudy:
    """A linearity study against known displacements, matched by key as ``mvpose validate``
    matches them."""
    keys = sorted(k for k in truth if k in measured)
    if not keys:
        raise GaugeError(f"no measurement matches the known displacements: truth keys "
                         f"{sorted(truth)[:5]}, measured keys {sorted(measured)[:5]}")
    ref = _characteristics([truth[k] for k in keys], recipe)
    meas = _characteristics([measured[k] for k in keys], recipe)
    chars = [Characteristic(name, unit, [float(v) for v in m], None, [float(v) for v in r])
             for (name, unit, r), (_, _, m) in zip(ref, meas, strict=True)]
    src = {**source, "keys": keys}
    return GaugeStudy("linearity", recipe.name, src, chars, [], title)
