"""Gauge capability studies on arrays: type 1 (Cg, Cgk, bias), type 3 (one-way ANOVA %GRR, ndc)
and linearity (bias regressed on the reference value). No I/O; docs/gauge.md has the sources.

Sources of the formulas (see docs/gauge.md for the full references):

- Type 1: Robert Bosch GmbH, *Booklet No. 10: Capability of Measurement and Test Processes*
  (2019), procedure 1, and VDA Volume 5 (2021) "Verfahren 1":
  ``Cg = (K/100 · T) / (L · s)`` and ``Cgk = (K/200 · T − |x̄ − xm|) / (L/2 · s)`` with
  K = 20 % and L = 6 (six standard deviations); the bias ``x̄ − xm`` is tested with Student's t
  on n − 1 degrees of freedom; ``%Var = K / Cg`` is the tolerance share the repeatability takes.
  Published example: the type-1 example of Thomas Roth's vignette *Working with the qualityTools
  package* (CRAN qualityTools 1.55, Figure 3): Cg 1.08, Cgk 0.91, t 2.307, p 0.03, printed with
  the package's spread L = 2·Φ⁻¹(0.9973) = 5.5643; ``Type1Options(spread=5.5643…)`` gives them,
  our default L = 6 gives 1.00 and 0.84 (tests/mvpose_core/test_gauge.py).
- Type 3: AIAG *Measurement Systems Analysis*, 4th edition (2010), the ANOVA method, for a gauge
  without operator influence (Booklet 10 procedure 3): a one-way ANOVA of parts × repeats, whose
  within-part mean square is the repeatability (EV = GRR) and whose between-part mean square less
  it, per repeat, the part variation (PV). Spreads are 6σ (the 4th edition and Booklet 10; the
  3rd edition used 5.15σ). ``ndc = floor(1.41 · PV / GRR)``. No published no-operator example
  with its data and ANOVA results was at hand; its test derives the figures by hand.
- Linearity: AIAG MSA 4th edition, Chapter III Section B, the linearity study: every reading's
  bias regressed on its reference value by least squares; slope and intercept tested with t on
  g·m − 2 degrees of freedom. The manual's worked example (5 parts × 12 readings at 2, 4, 6, 8,
  10) gives slope −0.1317, intercept 0.7367, R² 0.71 (tests/mvpose_core/test_gauge.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from mvpose_core.transforms import Array

CAPABLE = 1.33  # Cg and Cgk a type-1 study needs (Booklet 10, VDA 5, AIAG)
GRR_ACCEPTABLE = 10.0  # %GRR at or below: acceptable (AIAG MSA 4th ed.)
GRR_CONDITIONAL = 30.0  # %GRR at or below: acceptable for some applications
NDC_MIN = 5  # distinct categories a type-3 study needs (AIAG MSA 4th ed.)
MIN_TYPE1 = 25  # repeats a type-1 study needs (Booklet 10: at least 25, better 50)


class GaugeError(ValueError):
    """The data cannot make the study; the message names the characteristic and what is wrong."""


@dataclass(frozen=True)
class Type1Options:
    k_percent: float = 20.0  # K: the share of the tolerance the gauge may use
    spread: float = 6.0  # L: the spread in standard deviations (6σ)
    alpha: float = 0.05  # significance level of the bias test
    min_n: int = MIN_TYPE1


@dataclass(frozen=True)
class Type1Result:
    """One characteristic of a type-1 study. Without a reference value there is no bias, no Cgk
    and no %Var with bias (``None``); the verdict is then on Cg alone and says so."""

    name: str
    unit: str
    values: tuple[float, ...]
    n: int
    mean: float
    std: float  # s, ddof = 1
    tolerance: float  # T, the tolerance's full width
    reference: float | None  # xm
    cg: float
    cgk: float | None
    bias: float | None  # x̄ − xm
    t: float | None  # bias / (s / √n)
    p: float | None  # two-sided
    bias_significant: bool | None  # p < alpha
    var_percent: float  # K / Cg, %: the tolerance share the repeatability takes
    var_bias_percent: float | None  # K / Cgk, %
    options: Type1Options

    @property
    def capable(self) -> bool:
        """Cg ≥ 1.33 and, with a reference, Cgk ≥ 1.33."""
        return self.cg >= CAPABLE and (self.cgk is None or self.cgk >= CAPABLE)


def _clean(values: Array | list[float], name: str) -> Array:
    x = np.asarray(values, dtype=float).reshape(-1)
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise GaugeError(f"{name}: value {bad + 1} is {float(x[bad])!r}")
    return x


def type1(values: Array | list[float], tolerance: float, reference: float | None = None, *,
          name: str = "x", unit: str = "", options: Type1Options | None = None) -> Type1Result:
    """A type-1 study of one characteristic: one part measured ``n ≥ 25`` times.

    ``tolerance`` is the full width T = USL − LSL; ``reference`` is the part's reference value
    xm (None: unknown, no bias and no Cgk).
    """
    opt = options or Type1Options()
    x = _clean(values, name)
    if len(x) < opt.min_n:
        raise GaugeError(f"{name}: a type-1 study needs at least {opt.min_n} measurements of "
                         f"one part, got {len(x)}")
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise GaugeError(f"{name}: the tolerance must be a positive width, got {tolerance!r}")
    if reference is not None and not math.isfinite(reference):
        raise GaugeError(f"{name}: the reference value is {reference!r}")
    n = len(x)
    mean = float(x.mean())
    s = float(x.std(ddof=1))
    if s == 0.0:
        raise GaugeError(f"{name}: all {n} values are equal ({mean:g}); the resolution is too "
                         "coarse for a type-1 study")
    k = opt.k_percent / 100.0
    cg = k * tolerance / (opt.spread * s)
    cgk = bias = t = p = None
    significant = None
    var_bias = None
    if reference is not None:
        bias = mean - reference
        cgk = (k / 2.0 * tolerance - abs(bias)) / (opt.spread / 2.0 * s)
        t = bias / (s / math.sqrt(n))
        p = float(2.0 * stats.t.sf(abs(t), df=n - 1))
        significant = p < opt.alpha
        var_bias = opt.k_percent / cgk if cgk > 0 else math.inf
    return Type1Result(
        name=name, unit=unit, values=tuple(float(v) for v in x), n=n, mean=mean, std=s,
        tolerance=float(tolerance), reference=reference, cg=cg, cgk=cgk, bias=bias, t=t, p=p,
        bias_significant=significant, var_percent=opt.k_percent / cg, var_bias_percent=var_bias,
        options=opt,
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
        grr = self.grr_tol_percent if self.grr_tol_percent is not None else self.grr_tv_percent
        if grr > GRR_CONDITIONAL:
            return "not acceptable"
        if self.ndc < NDC_MIN:
            return "not acceptable"
        return "acceptable" if grr <= GRR_ACCEPTABLE else "conditional"


def type3(values: Array | list[list[float]], tolerance: float | None = None, *,
          parts: list[str] | None = None, name: str = "x", unit: str = "",
          spread: float = 6.0) -> Type3Result:
    """A type-3 study of one characteristic: ``values[i, j]`` is part i's j-th repeat.

    One-way ANOVA (AIAG MSA 4th ed., ANOVA method without the appraiser terms):
    ``σ²_EV = MS_e``, ``σ²_PV = max(0, (MS_p − MS_e) / r)``.
    """
    x = np.asarray(values, dtype=float)
    if x.ndim != 2:
        raise GaugeError(f"{name}: expected values [parts, repeats], got shape {x.shape}")
    n, r = x.shape
    if n < 2 or r < 2:
        raise GaugeError(f"{name}: a type-3 study needs at least 2 parts × 2 repeats, got "
                         f"{n} × {r}")
    _clean(x, name)
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise GaugeError(f"{name}: the tolerance must be a positive width, got {tolerance!r}")
    labels = tuple(parts) if parts is not None else tuple(str(i + 1) for i in range(n))
    if len(labels) != n:
        raise GaugeError(f"{name}: {len(labels)} part names for {n} parts")
    part_means = x.mean(axis=1)
    grand = float(x.mean())
    ss_p = float(r * np.sum((part_means - grand) ** 2))
    ss_e = float(np.sum((x - part_means[:, None]) ** 2))
    df_p, df_e = n - 1, n * (r - 1)
    ms_p, ms_e = ss_p / df_p, ss_e / df_e
    if ms_e == 0.0:
        raise GaugeError(f"{name}: every part read the same value on every repeat; the "
                         "resolution is too coarse for a type-3 study")
    f = ms_p / ms_e
    p = float(stats.f.sf(f, df_p, df_e))
    ev = math.sqrt(ms_e)
    pv = math.sqrt(max(0.0, (ms_p - ms_e) / r))
    tv = math.hypot(ev, pv)
    return Type3Result(
        name=name, unit=unit, values=tuple(tuple(float(v) for v in row) for row in x),
        parts=labels, n_parts=n, repeats=r, ss_parts=ss_p, ss_error=ss_e, df_parts=df_p,
        df_error=df_e, ms_parts=ms_p, ms_error=ms_e, f=f, p=p, ev=ev, pv=pv, tv=tv,
        tolerance=tolerance, spread=spread, grr_tv_percent=100.0 * ev / tv,
        grr_tol_percent=None if tolerance is None else 100.0 * spread * ev / tolerance,
        ndc=int(math.floor(1.41 * pv / ev)),
    )


@dataclass(frozen=True)
class LinearityResult:
    """One characteristic of a linearity study: bias = reading − reference, regressed on the
    reference (AIAG MSA 4th ed.). Linearity is acceptable when neither the slope nor the
    intercept differs from zero at ``alpha`` (the bias = 0 line lies inside the bands)."""

    name: str
    unit: str
    reference: tuple[float, ...]
    bias: tuple[float, ...]
    n: int
    slope: float
    intercept: float
    r_squared: float
    s: float  # residual standard deviation, g·m − 2 degrees of freedom
    t_slope: float
    p_slope: float
    t_intercept: float
    p_intercept: float
    alpha: float
    levels: tuple[float, ...]  # distinct reference values
    level_bias: tuple[float, ...]  # average bias at each

    @property
    def acceptable(self) -> bool:
        return self.p_slope >= self.alpha and self.p_intercept >= self.alpha


def linearity(reference: Array | list[float], readings: Array | list[float], *,
              name: str = "x", unit: str = "", alpha: float = 0.05) -> LinearityResult:
    """A linearity study of one characteristic: ``readings[k]`` measured at ``reference[k]``."""
    ref = _clean(reference, f"{name} reference")
    y = _clean(readings, name)
    if ref.shape != y.shape:
        raise GaugeError(f"{name}: {len(ref)} reference values for {len(y)} readings")
    levels = np.unique(ref)
    if len(levels) < 2 or len(y) < 3:
        raise GaugeError(f"{name}: a linearity study needs readings at 2 or more reference "
                         f"values, got {len(y)} readings at {len(levels)}")
    bias = y - ref
    fit = stats.linregress(ref, bias)
    dof = len(y) - 2
    resid = bias - (fit.intercept + fit.slope * ref)
    s = float(math.sqrt(np.sum(resid**2) / dof)) if dof > 0 else math.nan
    t_a = fit.slope / fit.stderr if fit.stderr > 0 else math.copysign(math.inf, fit.slope)
    t_b = (fit.intercept / fit.intercept_stderr if fit.intercept_stderr > 0
           else math.copysign(math.inf, fit.intercept))
    return LinearityResult(
        name=name, unit=unit, reference=tuple(float(v) for v in ref),
        bias=tuple(float(v) for v in bias), n=len(y), slope=float(fit.slope),
        intercept=float(fit.intercept), r_squared=float(fit.rvalue**2), s=s,
        t_slope=float(t_a), p_slope=float(2.0 * stats.t.sf(abs(t_a), dof)),
        t_intercept=float(t_b), p_intercept=float(2.0 * stats.t.sf(abs(t_b), dof)),
        alpha=alpha, levels=tuple(float(v) for v in levels),
        level_bias=tuple(float(bias[ref == v].mean()) for v in levels),
    )
