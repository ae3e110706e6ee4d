"""A gauge study's report: one self-contained HTML page (plots as inline SVG) and a PDF
(matplotlib's PdfPages) with the same table, verdict and plots, for a quality engineer to sign."""

from __future__ import annotations

import html
import io
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from mvpose_core.gauge import CAPABLE, LinearityResult, Type1Result, Type3Result
from server.gauge.study import GaugeStudy, passed

Result = Type1Result | Type3Result | LinearityResult

TITLES = {"type1": "Type-1 gauge study (Cg, Cgk)",
          "type3": "Type-3 gauge study (%GRR, ndc; no operator influence)",
          "linearity": "Linearity and bias study"}
LIMITS = {
    "type1": f"capable when Cg ≥ {CAPABLE} and Cgk ≥ {CAPABLE} (K = 20 %, L = 6 s; Bosch Booklet "
             "10 procedure 1, VDA 5); the bias is significant when p < 0.05 (Student t, n − 1).",
    "type3": "acceptable when %GRR ≤ 10 %, conditional up to 30 %, and ndc ≥ 5 (AIAG MSA 4th "
             "ed.); GRR is the repeatability of a one-way ANOVA, spread 6σ (not 5.15σ).",
    "linearity": "acceptable when neither slope nor intercept of bias on reference differs from "
                 "0 at α = 0.05 (AIAG MSA 4th ed., linearity study).",
}
SOURCES = ("Robert Bosch GmbH, Booklet No. 10, Capability of Measurement and Test Processes "
           "(procedures 1 and 3); VDA Volume 5, Capability of Measurement Processes; AIAG, "
           "Measurement Systems Analysis, 4th edition (ANOVA method, linearity study). "
           "Formulas: docs/gauge.md.")


@dataclass(frozen=True)
class ReportHeader:
    """Who, what and when: shown at the top of both formats."""

    station: str
    study_id: int | None = None
    created_at: datetime | None = None
    created_by: str = ""
    hash: str = ""


def _f(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if not np.isfinite(v):
        return str(v)
    return f"{0.0 if round(v, digits) == 0 else v:.{digits}f}"  # no "-0.000"


def table(results: Sequence[Result]) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of the study's figures, one row per characteristic."""
    if results and isinstance(results[0], Type1Result):
        head = ["characteristic", "n", "x̄", "s", "xm", "T", "bias", "p", "Cg", "Cgk", "%Var",
                "verdict"]
        rows = [[f"{r.name} ({r.unit})", _f(r.n), _f(r.mean, 4), _f(r.std, 4),
                 _f(r.reference, 4), _f(r.tolerance), _f(r.bias, 4), _f(r.p), _f(r.cg, 2),
                 _f(r.cgk, 2), _f(r.var_percent, 1),
                 ("capable" if r.capable else "NOT capable")
                 + ("" if r.cgk is not None else " (Cg only: no reference)")]
                for r in results if isinstance(r, Type1Result)]
    elif results and isinstance(results[0], Type3Result):
        head = ["characteristic", "parts × r", "EV=GRR", "PV", "TV", "%GRR TV", "%GRR T",
                "ndc", "p (parts)", "verdict"]
        rows = [[f"{r.name} ({r.unit})", f"{r.n_parts} × {r.repeats}", _f(r.ev, 4),
                 _f(r.pv, 4), _f(r.tv, 4), _f(r.grr_tv_percent, 1), _f(r.grr_tol_percent, 1),
                 _f(r.ndc), _f(r.p), r.verdict] for r in results if isinstance(r, Type3Result)]
    else:
        head = ["characteristic", "n", "slope", "p", "intercept", "p", "R²", "s", "verdict"]
        rows = [[f"{r.name} ({r.unit})", _f(r.n), _f(r.slope, 4), _f(r.p_slope),
                 _f(r.intercept, 4), _f(r.p_intercept), _f(r.r_squared, 2), _f(r.s, 4),
                 "acceptable" if r.acceptable else "NOT acceptable"]
                for r in results if isinstance(r, LinearityResult)]
    return head, rows


def _plot(r: Result, axes: tuple[Axes, Axes]) -> None:
    a, b = axes
    if isinstance(r, Type1Result):
        x = np.asarray(r.values)
        centre = r.reference if r.reference is not None else r.mean
        lim = 0.1 * r.tolerance  # ± K/200 · T around the reference
        a.plot(np.arange(1, r.n + 1), x, "o-", ms=3, lw=0.8, color="#1f5f8b")
        a.axhline(centre, color="k", lw=0.8, label="xm" if r.reference is not None else "x̄")
        for y in (centre - lim, centre + lim):
            a.axhline(y, color="#b22222", lw=0.8, ls="--")
        a.set_title(f"{r.name}: run chart (±0.1·T dashed)", fontsize=9)
        a.set_xlabel("measurement", fontsize=8)
        a.set_ylabel(r.unit, fontsize=8)
        b.hist(x, bins=max(5, int(np.sqrt(r.n))), color="#1f5f8b", alpha=0.8)
        b.axvline(centre, color="k", lw=0.8)
        b.set_title(f"{r.name}: histogram  Cg {_f(r.cg, 2)}  Cgk {_f(r.cgk, 2)}", fontsize=9)
        b.set_xlabel(r.unit, fontsize=8)
    elif isinstance(r, Type3Result):
        v = np.asarray(r.values)
        for i, row in enumerate(v):
            a.plot([i + 1] * len(row), row, "o", ms=3, color="#1f5f8b")
        a.plot(np.arange(1, r.n_parts + 1), v.mean(axis=1), "k_", ms=12)
        a.set_xticks(np.arange(1, r.n_parts + 1), r.parts, fontsize=7, rotation=45)
        a.set_title(f"{r.name}: readings per part", fontsize=9)
        a.set_ylabel(r.unit, fontsize=8)
        dev = (v - v.mean(axis=1, keepdims=True)).reshape(-1)
        b.hist(dev, bins=max(5, int(np.sqrt(dev.size))), color="#1f5f8b", alpha=0.8)
        b.set_title(f"{r.name}: repeatability  %GRR {_f(r.grr_tv_percent, 1)} of TV  "
                    f"ndc {r.ndc}", fontsize=9)
        b.set_xlabel(f"reading − part mean ({r.unit})", fontsize=8)
    else:
        ref, bias = np.asarray(r.reference), np.asarray(r.bias)
        a.plot(ref, bias, "o", ms=3, color="#1f5f8b")
        a.plot(r.levels, r.level_bias, "D", ms=5, color="#b22222")
        xs = np.linspace(ref.min(), ref.max(), 50)
        a.plot(xs, r.intercept + r.slope * xs, "k-", lw=0.8)
        a.axhline(0.0, color="grey", lw=0.6)
        a.set_title(f"{r.name}: bias = {r.intercept:.4f} + {r.slope:.4f}·ref", fontsize=9)
        a.set_xlabel(f"reference ({r.unit})", fontsize=8)
        a.set_ylabel(f"bias ({r.unit})", fontsize=8)
        fitted = r.intercept + r.slope * ref
        b.plot(ref, bias - fitted, "o", ms=3, color="#1f5f8b")
        b.axhline(0.0, color="grey", lw=0.6)
        b.set_title(f"{r.name}: residuals  R² {_f(r.r_squared, 2)}", fontsize=9)
        b.set_xlabel(f"reference ({r.unit})", fontsize=8)
    for ax in axes:
        ax.tick_params(labelsize=7)


def figure(r: Result) -> Figure:
    fig = Figure(figsize=(8.0, 2.6))
    a, b = fig.subplots(1, 2)
    _plot(r, (a, b))
    fig.tight_layout()
    return fig


def _svg(fig: Figure) -> str:
    buf = io.StringIO()
    fig.savefig(buf, format="svg")
    text = buf.getvalue()
    return text[text.index("<svg"):]


def _verdict(study: GaugeStudy, results: Sequence[Result]) -> str:
    return ("PASSED: every characteristic meets its limit" if passed(results)
            else "FAILED: a characteristic misses its limit (see the verdict column)")


STYLE = ("table.gauge{border-collapse:collapse;font-size:.9em}table.gauge td,table.gauge th{"
         "border:1px solid #999;padding:.2em .5em;text-align:right}table.gauge td:first-child,"
         "table.gauge th:first-child{text-align:left}.pass{color:#0a6b0a}.fail{color:#b22222}"
         ".verdict{font-size:1.3em;font-weight:bold}figure.gauge svg{max-width:100%;height:auto}")


def fragment(study: GaugeStudy, header: ReportHeader) -> str:
    """The report's body (meta, verdict, limits, figures, plots) as HTML, for the report and
    the operator page's study view."""
    results = study.results()
    head, rows = table(results)
    esc = html.escape
    ok = passed(results)
    meta = [("station", header.station), ("recipe", study.recipe),
            ("study", "" if header.study_id is None else str(header.study_id)),
            ("created", "" if header.created_at is None
             else header.created_at.isoformat(timespec="seconds")),
            ("by", header.created_by), ("measurements", _source_text(study)),
            ("record hash", header.hash)]
    return "".join([
        f"<h2>{esc(study.title)}</h2>" if study.title else "",
        "<table class='gauge meta'>" + "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>"
                                               for k, v in meta) + "</table>",
        f"<p class='verdict {'pass' if ok else 'fail'}'>{esc(_verdict(study, results))}</p>",
        f"<p>{esc(LIMITS[study.kind])}</p>",
        "<table class='gauge figures'><tr>" + "".join(f"<th>{esc(h)}</th>" for h in head)
        + "</tr>",
        *("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in rows),
        "</table><h3>Plots</h3>",
        *(f"<figure class='gauge'>{_svg(figure(r))}</figure>" for r in results),
        f"<h3>Sources</h3><p>{esc(SOURCES)}</p>",
    ])


def to_html(study: GaugeStudy, header: ReportHeader) -> str:
    """The report as one self-contained HTML page."""
    title = html.escape(TITLES[study.kind])
    return "".join([
        f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{title}</title>",
        "<style>body{font-family:sans-serif;margin:2em;max-width:62em}",
        STYLE, ".sign td{height:2.5em;min-width:14em;text-align:left}</style></head><body>",
        f"<h1>{title}</h1>", fragment(study, header),
        "<h3>Sign-off</h3><table class='gauge sign'><tr><th>quality engineer</th><td></td>"
        "<th>date</th><td></td><th>signature</th><td></td></tr></table></body></html>",
    ])


def _source_text(study: GaugeStudy) -> str:
    src = ", ".join(f"{k} {v}" for k, v in study.source.items() if k != "keys" and v)
    n = len(study.records)
    return f"{src}{'; ' if src and n else ''}{f'{n} stored records' if n else ''}"


def first_page(study: GaugeStudy, header: ReportHeader) -> Figure:
    """The PDF's first page (A4 landscape): header, verdict, limits, table, sources, sign-off."""
    results = study.results()
    head, rows = table(results)
    page = Figure(figsize=(11.69, 8.27))
    y = 0.95
    page.text(0.04, y, TITLES[study.kind], fontsize=16, weight="bold")
    y -= 0.04
    if study.title:
        page.text(0.04, y, study.title, fontsize=11)
        y -= 0.03
    meta = (f"station {header.station}   recipe {study.recipe}   study "
            f"{header.study_id if header.study_id is not None else '–'}   created "
            f"{header.created_at.isoformat(timespec='seconds') if header.created_at else '–'}"
            f" by {header.created_by or '–'}")
    page.text(0.04, y, meta, fontsize=9)
    y -= 0.03
    page.text(0.04, y, f"measurements: {_source_text(study)}", fontsize=9)
    y -= 0.03
    if header.hash:
        page.text(0.04, y, f"record hash (sha256 chain): {header.hash}", fontsize=8,
                  family="monospace")
        y -= 0.04
    ok = passed(results)
    page.text(0.04, y, _verdict(study, results), fontsize=14, weight="bold",
              color="#0a6b0a" if ok else "#b22222")
    y -= 0.035
    page.text(0.04, y, LIMITS[study.kind], fontsize=8, wrap=True)
    y -= 0.03
    ax = page.add_axes((0.04, 0.16, 0.92, max(0.1, y - 0.18)))
    ax.axis("off")
    first = 0.13
    widths = [first] + [(1.0 - first) / (len(head) - 1)] * (len(head) - 1)
    tab = ax.table(cellText=rows, colLabels=head, colWidths=widths, loc="upper left",
                   cellLoc="right")
    tab.auto_set_font_size(False)
    tab.set_fontsize(7.5)
    tab.scale(1.0, 1.25)
    page.text(0.04, 0.10, "Sources: " + SOURCES, fontsize=7, wrap=True)
    page.text(0.04, 0.04, "quality engineer: ______________________   date: ___________"
              "   signature: ______________________", fontsize=10)
    return page


def first_page_png(study: GaugeStudy, header: ReportHeader, dpi: int = 110) -> bytes:
    """The PDF's first page as a PNG (for docs and the page's preview)."""
    buf = io.BytesIO()
    first_page(study, header).savefig(buf, format="png", dpi=dpi)
    return buf.getvalue()


def to_pdf(study: GaugeStudy, header: ReportHeader) -> bytes:
    """The report as a PDF: the first page (:func:`first_page`), then the plots, three
    characteristics a page."""
    results = study.results()
    buf = io.BytesIO()
    with PdfPages(buf, metadata={"Title": TITLES[study.kind], "Creator": "mvpose gauge"}) as pdf:
        page = first_page(study, header)
        pdf.savefig(page)
        for start in range(0, len(results), 3):
            fig = Figure(figsize=(8.27, 11.69))
            chunk = results[start:start + 3]
            grid = fig.subplots(3, 2)
            for row, r in zip(grid, chunk, strict=False):
                _plot(r, (row[0], row[1]))
            for row in grid[len(chunk):]:
                row[0].axis("off")
                row[1].axis("off")
            fig.tight_layout()
            pdf.savefig(fig)
    return buf.getvalue()
