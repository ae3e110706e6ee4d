"""The crossed gauge R&R ANOVA (parts × appraisers × trials) and type 3, its one-appraiser case."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from mvpose_core.gauge.base import GRR_ACCEPTABLE, GRR_CONDITIONAL, NDC_MIN, GaugeError, clean
from mvpose_core.transforms import Array

POOL_ALPHA = 0.25  # the interaction is pooled into repeatability when its p ≥ this (qualityTools)


@dataclass(frozen=True)
class AnovaTerm:
    """One row of an ANOVA table. F and p are against the repeatability mean square of the same
    table (the fixed-effects table R's ``aov`` prints, as the qualityTools vignette shows it)."""

    source: str  # "part", "appraiser", "part × appraiser", "repeatability"
    df: int
    ss: float
    ms: float
    f: float | None  # None for the repeatability row
    p: float | None


@dataclass(frozen=True)
class CrossedAnova:
    """A crossed gauge R&R: n parts × a appraisers × r trials, two-way ANOVA with interaction
    (AIAG MSA 4th ed., the ANOVA method). Variances are the variance components (σ²); with one
    appraiser there is no appraiser and no interaction term (a type-3 study)."""

    name: str
    n_parts: int
    appraisers: int
    trials: int
    table: tuple[AnovaTerm, ...]  # the full model
    reduced: tuple[AnovaTerm, ...] | None  # the model without interaction, when it was pooled
    pool_alpha: float
    var_repeatability: float  # σ²_EV
    var_appraiser: float  # σ²_AV (appraiser alone)
    var_interaction: float  # σ²_INT (0 when pooled)
    var_part: float  # σ²_PV
    tolerance: float | None
    spread: float  # σ multiple of the study variation (6)

    @property
    def pooled(self) -> bool:
        return self.reduced is not None

    def term(self, source: str, *, reduced: bool = False) -> AnovaTerm:
        rows = self.reduced if reduced and self.reduced is not None else self.table
        for t in rows:
            if t.source == source:
                return t
        raise KeyError(f"no ANOVA row {source!r}; the rows are {[t.source for t in rows]}")

    @property
    def var_reproducibility(self) -> float:
        return self.var_appraiser + self.var_interaction

    @property
    def var_grr(self) -> float:
        return self.var_repeatability + self.var_reproducibility

    @property
    def var_total(self) -> float:
        return self.var_grr + self.var_part

    def sd(self, component: str) -> float:
        """σ of ``repeatability``, ``reproducibility``, ``appraiser``, ``interaction``, ``grr``,
        ``part`` or ``total``."""
        return math.sqrt(getattr(self, f"var_{component}"))

    def contribution(self, component: str) -> float:
        """%Contribution: the component's share of the total variance."""
        return 100.0 * getattr(self, f"var_{component}") / self.var_total

    def study_var(self, component: str) -> float:
        """%Study Var (%TV): the component's σ over the total σ."""
        return 100.0 * self.sd(component) / self.sd("total")

    def tolerance_percent(self, component: str) -> float | None:
        """%Tolerance: spread · σ of the component over the tolerance's full width."""
        if self.tolerance is None:
            return None
        return 100.0 * self.spread * self.sd(component) / self.tolerance

    @property
    def ndc(self) -> int:
        """floor(1.41 · PV / GRR) (AIAG MSA 4th ed.)."""
        return int(math.floor(1.41 * self.sd("part") / self.sd("grr")))

    @property
    def verdict(self) -> str:
        return _grr_verdict(self.tolerance_percent("grr"), self.study_var("grr"), self.ndc)


def _grr_verdict(grr_tol: float | None, grr_tv: float, ndc: int) -> str:
    grr = grr_tol if grr_tol is not None else grr_tv
    if grr > GRR_CONDITIONAL or ndc < NDC_MIN:
        return "not acceptable"
    return "acceptable" if grr <= GRR_ACCEPTABLE else "conditional"


def _table(terms: list[tuple[str, int, float]], ss_e: float, df_e: int) -> tuple[AnovaTerm, ...]:
    ms_e = ss_e / df_e
    rows = [AnovaTerm(src, df, ss, ss / df, ss / df / ms_e,
                      float(stats.f.sf(ss / df / ms_e, df, df_e))) for src, df, ss in terms]
    return (*rows, AnovaTerm("repeatability", df_e, ss_e, ms_e, None, None))


def crossed_anova(values: Array | list[list[list[float]]], tolerance: float | None = None, *,
                  name: str = "x", spread: float = 6.0,
                  pool_alpha: float = POOL_ALPHA) -> CrossedAnova:
    """A crossed gauge R&R of one characteristic: ``values[i, j, k]`` is part i read by
    appraiser j on trial k (AIAG MSA 4th ed., ANOVA method; VDA 5 / Booklet 10 procedure 2).

    Variance components of the random model: ``σ²_EV = MS_e``, ``σ²_INT = (MS_pa − MS_e)/r``,
    ``σ²_AV = (MS_a − MS_pa)/(n·r)``, ``σ²_PV = (MS_p − MS_pa)/(a·r)``, each at least 0. The
    interaction is pooled into repeatability when its p ≥ ``pool_alpha`` or its variance
    component is negative (the rule of qualityTools' ``gageRR``, alpha = 0.25): MS_e is then
    the pooled (SS_pa + SS_e)/(df_pa + df_e) and MS_pa is replaced by it.
    """
    x = np.asarray(values, dtype=float)
    if x.ndim != 3:
        raise GaugeError(f"{name}: expected values [parts, appraisers, trials], got shape "
                         f"{x.shape}")
    n, a, r = x.shape
    if n < 2 or a < 1 or r < 2:
        raise GaugeError(f"{name}: a gauge R&R needs at least 2 parts × 1 appraiser × 2 trials, "
                         f"got {n} × {a} × {r}")
    if not np.all(np.isfinite(x)):
        i, j, k = (int(v) for v in np.argwhere(~np.isfinite(x))[0])
        raise GaugeError(f"{name}: part {i + 1}, appraiser {j + 1}, trial {k + 1} is "
                         f"{float(x[i, j, k])!r}")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise GaugeError(f"{name}: the tolerance must be a positive width, got {tolerance!r}")
    if not 0.0 <= pool_alpha <= 1.0:
        raise GaugeError(f"{name}: pool_alpha is a probability, got {pool_alpha!r}")
    grand = float(x.mean())
    m_p, m_a, m_pa = x.mean(axis=(1, 2)), x.mean(axis=(0, 2)), x.mean(axis=2)
    ss_p = float(a * r * np.sum((m_p - grand) ** 2))
    ss_a = float(n * r * np.sum((m_a - grand) ** 2))
    ss_pa = float(r * np.sum((m_pa - m_p[:, None] - m_a[None, :] + grand) ** 2))
    ss_e = float(np.sum((x - m_pa[:, :, None]) ** 2))
    df_p, df_a, df_pa, df_e = n - 1, a - 1, (n - 1) * (a - 1), n * a * (r - 1)
    if ss_e == 0.0:
        raise GaugeError(f"{name}: every part read the same value on every repeat; the "
                         "resolution is too coarse for a gauge study")
    if a == 1:
        table = _table([("part", df_p, ss_p)], ss_e, df_e)
        ms_e = ss_e / df_e
        return CrossedAnova(name, n, a, r, table, None, pool_alpha, ms_e, 0.0, 0.0,
                            max(0.0, (table[0].ms - ms_e) / r), tolerance, spread)
    table = _table([("appraiser", df_a, ss_a), ("part", df_p, ss_p),
                    ("part × appraiser", df_pa, ss_pa)], ss_e, df_e)
    ms_a, ms_p, ms_pa, ms_e = (t.ms for t in table)
    reduced = None
    p_pa = table[2].p
    if ms_pa < ms_e or (p_pa is not None and p_pa >= pool_alpha):
        reduced = _table([("appraiser", df_a, ss_a), ("part", df_p, ss_p)], ss_pa + ss_e,
                         df_pa + df_e)
        ms_e = ms_pa = reduced[-1].ms
    return CrossedAnova(
        name, n, a, r, table, reduced, pool_alpha, var_repeatability=ms_e,
        var_appraiser=max(0.0, (ms_a - ms_pa) / (n * r)),
        var_interaction=max(0.0, (ms_pa - ms_e) / r),
        var_part=max(0.0, (ms_p - ms_pa) / (a * r)), tolerance=tolerance, spread=spread,
    )


@dataclass(frozen=True)
class Type3Result:
    """One characteristic of a type-3 study (no operator influence): n parts × r repeats."""

    name: str
    unit: str
    values: tuple[tuple[float, ...], ...]  # [part][repeat]
    parts: tuple[str, ...]
    n_parts: int
    repeats: int
    ss_parts: float
    ss_error: float
    df_parts: int
    df_error: int
    ms_parts: float
    ms_error: float
    f: float
    p: float
    ev: float  # σ of repeatability (= GRR without operators)
    pv: float  # σ of the parts
    tv: float  # √(GRR² + PV²)
    tolerance: float | None
    spread: float  # 6 (σ multiple of the %GRR against the tolerance)
    grr_tv_percent: float  # 100 · GRR / TV
    grr_tol_percent: float | None  # 100 · spread · GRR / T
    ndc: int

    @property
    def grr(self) -> float:
        return self.ev

    @property
    def verdict(self) -> str:
        """``acceptable`` / ``conditional`` / ``not acceptable`` by the %GRR that decides (against
        the tolerance when there is one, else against TV) and ndc ≥ 5 (AIAG MSA 4th ed.)."""
        return _grr_verdict(self.grr_tol_percent, self.grr_tv_percent, self.ndc)


def type3(values: Array | list[list[float]], tolerance: float | None = None, *,
          parts: list[str] | None = None, name: str = "x", unit: str = "",
          spread: float = 6.0) -> Type3Result:
    """A type-3 study of one characteristic: ``values[i, j]`` is part i's j-th repeat.

    The one-appraiser case of :func:`crossed_anova` (a one-way ANOVA of parts × repeats):
    ``σ²_EV = MS_e``, ``σ²_PV = max(0, (MS_p − MS_e) / r)``, GRR = EV.
    """
    x = np.asarray(values, dtype=float)
    if x.ndim != 2:
        raise GaugeError(f"{name}: expected values [parts, repeats], got shape {x.shape}")
    n, r = x.shape
    if n < 2 or r < 2:
        raise GaugeError(f"{name}: a type-3 study needs at least 2 parts × 2 repeats, got "
                         f"{n} × {r}")
    clean(x, name)
    labels = tuple(parts) if parts is not None else tuple(str(i + 1) for i in range(n))
    if len(labels) != n:
        raise GaugeError(f"{name}: {len(labels)} part names for {n} parts")
    res = crossed_anova(x[:, None, :], tolerance, name=name, spread=spread)
    part, err = res.term("part"), res.term("repeatability")
    return Type3Result(
        name=name, unit=unit, values=tuple(tuple(float(v) for v in row) for row in x),
        parts=labels, n_parts=n, repeats=r, ss_parts=part.ss, ss_error=err.ss,
        df_parts=part.df, df_error=err.df, ms_parts=part.ms, ms_error=err.ms,
        f=float(part.f or 0.0), p=float(part.p or 0.0), ev=res.sd("grr"), pv=res.sd("part"),
        tv=res.sd("total"), tolerance=tolerance, spread=spread,
        grr_tv_percent=res.study_var("grr"), grr_tol_percent=res.tolerance_percent("grr"),
        ndc=res.ndc,
    )
