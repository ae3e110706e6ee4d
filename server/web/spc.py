"""The SPC page's charts, built from the reader's columns with mvpose_core.spc: per offset axis,
per camera's RMS residual and for the cycle time an I-MR chart, its limits from a baseline, the
run rules' points and the capability over the window. Limits, rules and capability use every
point; only the drawn series is thinned (min and max per bucket) when it has more points than a
chart can show."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np

from mvpose_core.spc import RULES, capability, imr_limits, nelson
from server.web.i18n import N_, _, when

#: mvpose_core.spc's rule names, for the catalogue (the page shows them translated)
RULE_NAMES = (
    N_("1 point beyond 3σ"), N_("9 points in a row on one side of the centre line"),
    N_("6 points in a row steadily increasing or decreasing"),
    N_("14 points in a row alternating up and down"),
    N_("2 of 3 points in a row beyond 2σ on one side"),
    N_("4 of 5 points in a row beyond 1σ on one side"),
    N_("15 points in a row within 1σ of the centre line"),
    N_("8 points in a row beyond 1σ, on either side"))

#: points a chart draws at most; beyond, each bucket's min and max are drawn (flagged points
#: always are)
DRAWN = 4000
#: flagged points listed under a chart per rule (the newest); all are counted and marked
LISTED = 20
#: the baseline without a time range: the first points of the window
BASELINE_POINTS = 50


@dataclass(frozen=True)
class Baseline:
    """Which points the control limits come from: the first ``points`` of each series, or the
    points triggered in [since, until] when either is given."""

    points: int = BASELINE_POINTS
    since: datetime | None = None
    until: datetime | None = None

    def mask(self, t: np.ndarray) -> np.ndarray:
        if self.since is None and self.until is None:
            m = np.zeros(t.size, dtype=bool)
            m[: self.points] = True
            return m
        lo = self.since.timestamp() if self.since else -np.inf
        hi = self.until.timestamp() if self.until else np.inf
        return (t >= lo) & (t <= hi)

    def words(self) -> str:
        if self.since is None and self.until is None:
            return _("the first {n} points of the window").format(n=self.points)
        a = when(self.since) if self.since else _("the window's start")
        b = when(self.until) if self.until else _("its end")
        return _("the points from {a} to {b}").format(a=a, b=b)


def _r(x: float | None, digits: int = 6) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), digits)


def thin(n: int, keep: np.ndarray, values: np.ndarray, most: int = DRAWN) -> np.ndarray:
    """Indices to draw: all when ``n <= most``, else each bucket's min and max and ``keep``."""
    if n <= most:
        return np.arange(n)
    edges = np.linspace(0, n, most // 2 + 1).astype(int)
    picks = [keep]
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        if b > a:
            seg = values[a:b]
            picks.append(np.array([a + int(np.argmin(seg)), a + int(np.argmax(seg))]))
    return np.unique(np.concatenate(picks))


def chart(key: str, title: str, unit: str, ids: list[int], t: list[float],
          values: list[float | None], lsl: float | None, usl: float | None,
          baseline: Baseline) -> dict[str, Any]:
    """One I-MR chart of a column (None values, NOK results', left out)."""
    have = [k for k, v in enumerate(values) if v is not None]
    x = np.array([values[k] for k in have], dtype=float)
    tt = np.array([t[k] for k in have], dtype=float)
    rid = [ids[k] for k in have]
    out: dict[str, Any] = {"key": key, "title": title, "unit": unit, "points": int(x.size),
                           "lsl": lsl, "usl": usl, "limits": None, "capability": None,
                           "rules": [], "t": [], "values": [], "mr": [], "flagged": []}
    if x.size == 0:
        out["message"] = _("no values in this window")
        return out
    base = baseline.mask(tt)
    if base.sum() < 2:
        out["message"] = _("the baseline ({baseline}) holds {n} value(s) of this series: no "
                           "control limits (2 needed)").format(baseline=baseline.words(),
                                                               n=int(base.sum()))
        flags: dict[int, list[int]] = {}
    else:
        lim = imr_limits(x[base])
        out["limits"] = {"center": _r(lim.center), "ucl": _r(lim.ucl), "lcl": _r(lim.lcl),
                         "mr_center": _r(lim.range_center), "mr_ucl": _r(lim.range_ucl),
                         "sigma_within": _r(lim.sigma_within), "baseline_points": lim.n,
                         "baseline_from": float(tt[base][0]),
                         "baseline_to": float(tt[base][-1])}
        flags = nelson(x, lim.center, lim.sigma_within)
    if x.size >= 2 and (lsl is not None or usl is not None):
        c = capability(x, lsl, usl)
        out["capability"] = {"cp": _r(c.cp, 3), "cpk": _r(c.cpk, 3), "pp": _r(c.pp, 3),
                             "ppk": _r(c.ppk, 3), "mean": _r(c.mean),
                             "sigma_within": _r(c.sigma_within),
                             "sigma_overall": _r(c.sigma_overall), "n": c.n}
    hit = sorted({i for idx in flags.values() for i in idx})
    for number, idx in flags.items():
        if idx:
            rule = RULES[number]
            out["rules"].append({
                "rule": number, "name": _(rule.name), "western_electric": rule.western_electric,
                "count": len(idx),
                "points": [{"id": rid[i], "t": float(tt[i]), "value": _r(float(x[i]))}
                           for i in idx[-LISTED:]]})
    mr = np.concatenate([[np.nan], np.abs(np.diff(x))])
    drawn = thin(x.size, np.array(hit, dtype=int), x)
    flagged = set(hit)
    out["t"] = [float(tt[i]) for i in drawn]
    out["values"] = [_r(float(x[i])) for i in drawn]
    out["mr"] = [_r(float(mr[i])) for i in drawn]
    out["flagged"] = [_r(float(x[i])) if i in flagged else None for i in drawn]
    return out


def spc_charts(cols: dict[str, Any], tol: dict[str, Any],
               baseline: Baseline) -> list[dict[str, Any]]:
    """Every chart of the page: the offset axes, each camera's RMS residual, the cycle time."""
    labels = tol.get("labels") or ["X", "Y", "Z", "W", "P", "R"]
    units = tol.get("units") or ["mm", "mm", "mm", "°", "°", "°"]
    charts = []
    for k, values in enumerate(cols["offset"]):
        label = labels[k] if k < len(labels) else _("axis {n}").format(n=k + 1)
        unit = units[k] if k < len(units) else ""
        lim = tol.get("max_offset_deg") if unit == "°" else tol.get("max_offset_mm")
        title = _("Offset {axis} ({unit})").format(axis=label, unit=unit)
        charts.append(chart(f"offset.{label}", title, unit, cols["id"], cols["t"], values,
                            -lim if lim is not None else None, lim, baseline))
    for cam in cols["cameras"]:
        title = _("RMS residual, camera {camera} (px)").format(camera=cam)
        charts.append(chart(f"rms.{cam}", title, "px", cols["id"], cols["t"],
                            cols["camera_rms"][cam], None, tol.get("max_rms_px"), baseline))
    charts.append(chart("cycle.total", _("Cycle time (ms)"), "ms", cols["id"], cols["t"],
                        cols["total_ms"], None, tol.get("deadline_ms"), baseline))
    return charts
