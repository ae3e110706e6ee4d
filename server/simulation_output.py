"""Files of ``mvpose simulate``: one CSV and one PNG per study, the paper's stated values marked."""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter

from mvpose_core.simulation.montecarlo import PointSummary
from mvpose_core.simulation.planning import Accuracy, StationPlan
from mvpose_core.simulation.studies import Study

CSV_FIELDS = [f.name for f in dataclasses.fields(PointSummary)]
_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple")


def write_csv(path: Path, rows: Sequence[PointSummary]) -> None:
    """One row per point and objective; floats with 6 significant digits."""
    with path.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(CSV_FIELDS)
        for r in rows:
            w.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in dataclasses.astuple(r)])


def read_csv(path: Path) -> list[PointSummary]:
    """Rows written by :func:`write_csv` (for docs and tests)."""
    types = {f.name: f.type for f in dataclasses.fields(PointSummary)}
    convert: dict[object, Callable[[str], Any]] = {"str": str, "int": int, "float": float}
    with path.open(newline="", encoding="utf-8") as fh:
        return [
            PointSummary(**{k: convert[types[k]](v) for k, v in row.items()})
            for row in csv.DictReader(fh)
        ]


def plot_study(path: Path, study: Study, rows: Sequence[PointSummary], command: str) -> None:
    """RMS rotation and translation error against x; bound dotted, the paper's values in red."""
    fig = Figure(figsize=(11, 5.6), layout="constrained")
    axes = fig.subplots(1, 2)
    log = study.name == "views"  # hand-eye error spans two decades there
    for ax, (field, bound, unit) in zip(
        axes,
        (
            ("rot_rms", "bound_rot", "rotation error [°]"),
            ("trans_rms", "bound_trans", "translation error [mm]"),
        ),
        strict=True,
    ):
        for colour, series in zip(_COLOURS, study.series, strict=False):
            for objective, style, tag in (
                ("all", "-o", "both cameras"),
                ("left_only", "--s", "left camera (paper)"),
            ):
                pts = sorted(
                    (r for r in rows if r.series == series and r.objective == objective),
                    key=lambda r: r.x,
                )
                if not pts:
                    continue
                xs = [r.x for r in pts]
                label = f"{series}: {tag}" if len(study.series) > 1 else tag
                ax.plot(
                    xs,
                    [getattr(r, field) for r in pts],
                    style,
                    color=colour,
                    ms=4,
                    label=label,
                    alpha=1.0 if objective == "all" else 0.7,
                )
                if objective == "all":
                    ax.plot(
                        xs,
                        [getattr(r, bound) for r in pts],
                        ":",
                        color=colour,
                        lw=1.2,
                        label=f"{series}: Cramér–Rao bound"
                        if len(study.series) > 1
                        else "Cramér–Rao bound (both)",
                    )
        _paper_marks(ax, study, field == "rot_rms", max(r.x for r in rows))
        ax.set_xlabel(study.x_label)
        ax.set_ylabel(f"RMS {unit}")
        if log:
            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
            ax.yaxis.set_minor_formatter(FormatStrFormatter("%g"))
        else:
            ax.set_ylim(bottom=0)
        ax.grid(True, alpha=0.3)
    handles, labels = axes[1].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=3, fontsize=7, frameon=False)
    fig.suptitle(f"{study.title}\n{command}", fontsize=9)
    fig.savefig(path, dpi=110)


def _paper_marks(ax: Axes, study: Study, rotation: bool, x_max: float) -> None:
    for m in study.paper:
        value = m.rot_deg if rotation else m.trans_mm
        if m.kind == "point" and value is not None:
            ax.plot([m.x], [value], "r*", ms=12, label=m.label)
        elif m.kind == "ceiling" and value is not None:
            ax.hlines(value, m.x, x_max, colors="red", linestyles="-.", label=m.label)
        elif m.kind == "flat_from":
            ax.axvline(m.x, color="grey", ls="--", lw=1, label=m.label)


def plan_report(plan: StationPlan) -> str:
    """The plan as text: figures, verdict, and the loss ranking."""

    def fig(a: Accuracy | None) -> str:
        if a is None:
            return "pose not determined"
        return f"{a.rot_deg:.3f}° {a.trans_mm:.3f} mm"

    tol = plan.tolerance
    he = plan.handeye
    left = (
        fig(plan.bound_left_only)
        if plan.bound_left_only is not None or plan.robot_mounted
        else "n/a (fixed cameras: the paper's left-camera objective is for a robot-mounted rig)"
    )
    lines = [
        f"station {plan.station}, recipe {plan.recipe}: {len(plan.marks)} marks, "
        f"{len(plan.cameras)} cameras, {plan.observations} observations, σ = {plan.sigma_px:g} px",
        "1σ at the grasp point (RMS magnitude):",
        f"  Cramér–Rao bound, all cameras       {fig(plan.bound)}",
        f"  Cramér–Rao bound, left camera only  {left}",
        f"  Monte Carlo, {plan.trials} trials{' ' * max(0, 15 - len(str(plan.trials)))}"
        f"{fig(plan.monte_carlo)}"
        + (f"  ({plan.failed} failed)" if plan.failed else "")
        + (
            f"  with hand-eye {he.name} ({he.rot_deg}°/{he.trans_mm} mm per view)"
            if he.rot_deg or he.trans_mm
            else ""
        ),
        f"  tolerance                           {tol.rot_deg:g}° {tol.trans_mm:g} mm",
        f"verdict: {'MEETS' if plan.meets_tolerances else 'DOES NOT MEET'} the recipe tolerances",
        "if one is lost (worst first; bound at the grasp point, load = share of tolerance):",
    ]
    for loss in plan.losses:
        load = "" if loss.bound is None else f"  load {loss.bound.load(tol):.2f}"
        ok = "" if loss.bound is None or loss.bound.within(tol) else "  OUT OF TOLERANCE"
        lines.append(f"  {loss.kind:6} {loss.name:12} {fig(loss.bound)}{load}{ok}")
    lines.extend(f"warning: {w}" for w in plan.warnings)
    return "\n".join(lines)
