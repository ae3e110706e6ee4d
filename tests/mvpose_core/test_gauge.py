"""The gauge formulas against published worked examples (linearity, type 1, the crossed gauge
R&R ANOVA whose one-appraiser case is type 3) and hand-derived ones (type 3).

Published: AIAG, *Measurement Systems Analysis*, 4th edition (2010), Chapter III Section B, the
linearity example: five parts with reference values 2, 4, 6, 8, 10, each read 12 times. The
readings are those printed in the manual, as the CRAN packages qualityTools and r6qualitytools
reproduce them in the example of ``gageLinDesign``
(https://rdocumentation.org/packages/r6qualitytools/versions/1.0.1/topics/gageLinDesign); the
manual prints the fitted line y = 0.7367 − 0.1317 x, R² 0.71, and the bias averages 0.491667,
0.125, 0.025, −0.291667, −0.616667 (quoted in the Elsmar forum thread "Linearity Analysis - AIAG's
MSA Manual 3rd Edition - Question", where the same example appears).

Published: Thomas Roth, *Working with the qualityTools package* (the vignette of the CRAN package
qualityTools 1.55, 2016), section "Gage Capability - MSA Type I", its Figure 3 "Potentially
capable gage with bias": 25 readings of one unit (printed in the vignette's code), target
10.003, tolerance 9.903 to 10.103; the figure prints x̄ = 10.01, s = 0.01, Cg = 1.08, Cgk = 0.91,
t-value 2.307, p-value 0.03. Read here in the vignette's source and PDF (github.com/cran/
qualityTools, inst/doc/qualityTools.rnw and .pdf) and again in r6qualitytools' rendering of the
same example (github.com/Fabianenc/r6qualitytools, man/cg.Rd and docs/reference/cg-1.png). Its
convention differs from ours in one place, stated in the test below.

Published: the same vignette, section 3.2 "Gage Repeatability&Reproducibility - MSA Type II"
(a crossed gauge R&R: 10 parts × 3 operators × 2 measurements, its 60 readings printed in the
vignette's code): the ANOVA table printed by ``gageRR`` (Df, Sum Sq, Mean Sq, F value, Pr(>F) of
Operator, Part, Operator:Part and Residuals) and, in its paragraph "Components of variation" and
the text under Figure 4, the variance components (totalRR 1.664 = repeatability 1.209 +
reproducibility 0.455, Part to Part 1.781, total 3.446) and their contributions (48 %, 35 %,
13 %, 51.7 %). Read in the PDF (inst/doc/qualityTools.pdf, its text streams decompressed) and
the source (inst/doc/qualityTools.rnw) at github.com/cran/qualityTools, version 1.55. A type-3
study is that ANOVA's one-appraiser case (``type3`` calls ``crossed_anova``). No published
no-operator example with its data and ANOVA results could be read; type 3 is also tested against
values derived by hand below (closed forms in the comments) and against scipy's one-way ANOVA.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from mvpose_core.gauge import (
    GaugeError,
    Type1Options,
    crossed_anova,
    linearity,
    type1,
    type3,
)

AIAG_LINEARITY = {
    2.0: [2.7, 2.5, 2.4, 2.5, 2.7, 2.3, 2.5, 2.5, 2.4, 2.4, 2.6, 2.4],
    4.0: [5.1, 3.9, 4.2, 5.0, 3.8, 3.9, 3.9, 3.9, 3.9, 4.0, 4.1, 3.8],
    6.0: [5.8, 5.7, 5.9, 5.9, 6.0, 6.1, 6.0, 6.1, 6.4, 6.3, 6.0, 6.1],
    8.0: [7.6, 7.7, 7.8, 7.7, 7.8, 7.8, 7.8, 7.7, 7.8, 7.5, 7.6, 7.7],
    10.0: [9.1, 9.3, 9.5, 9.3, 9.4, 9.5, 9.5, 9.5, 9.6, 9.2, 9.3, 9.4],
}


def test_linearity_matches_the_aiag_msa_example_to_its_printed_digits() -> None:
    ref = [r for r, ys in AIAG_LINEARITY.items() for _ in ys]
    readings = [y for ys in AIAG_LINEARITY.values() for y in ys]
    res = linearity(ref, readings)
    assert round(res.slope, 4) == -0.1317
    assert round(res.intercept, 4) == 0.7367
    assert round(res.r_squared, 2) == 0.71
    assert [round(b, 6) for b in res.level_bias] == [0.491667, 0.125, 0.025, -0.291667,
                                                      -0.616667]
    # The t statistics are the regression's (independent computation: scipy's linregress).
    fit = stats.linregress(ref, np.subtract(readings, ref))
    assert res.t_slope == pytest.approx(fit.slope / fit.stderr, rel=1e-12)
    assert res.t_intercept == pytest.approx(fit.intercept / fit.intercept_stderr, rel=1e-12)
    assert not res.acceptable  # the manual's conclusion: the gauge has a linearity problem


# qualityTools vignette, section "Gage Capability - MSA Type I" (order as printed there)
QT_TYPE1 = [9.991, 10.013, 10.001, 10.007, 10.010, 10.013, 10.008, 10.017, 10.005, 10.005,
            10.002, 10.017, 10.005, 10.002, 9.996, 10.011, 10.009, 10.006, 10.008, 10.003,
            10.002, 10.006, 10.010, 9.992, 10.013]


def test_type1_matches_the_qualitytools_vignette_example_to_its_printed_digits() -> None:
    # The vignette states Cg = 0.2·T / (6·s) with K = 20 % as we do (VDA 5, Booklet 10), and its
    # Cgk = (0.1·T − |bias|) / (L/2 · s) is ours too. Its printed figures, though, come from the
    # package's code, whose reference spread L·s is the 99.73 % quantile minus the 0.27 %
    # quantile of N(x̄, s): L = 2·Φ⁻¹(Φ(3) − Φ(−3)) = 5.5643 rather than 6. Type1Options.spread
    # is that L, so their convention is ours with one option changed.
    their_spread = 2.0 * float(stats.norm.ppf(stats.norm.cdf(3.0) - stats.norm.cdf(-3.0)))
    assert round(their_spread, 4) == 5.5643
    tol = 10.103 - 9.903
    theirs = type1(QT_TYPE1, tol, 10.003, options=Type1Options(spread=their_spread))
    assert theirs.n == 25
    assert round(theirs.mean, 2) == 10.01 and round(theirs.std, 2) == 0.01
    assert round(theirs.cg, 2) == 1.08
    assert round(theirs.cgk or 0, 2) == 0.91
    assert round(theirs.t or 0, 3) == 2.307  # "H0: Bias = 0, t-value: 2.307, p-value: 0.03"
    assert round(theirs.p or 0, 2) == 0.03
    assert theirs.bias_significant is True
    # Our default (L = 6, VDA 5 / Booklet 10) on the same readings: Cg = 0.04 / (6·s) and
    # Cgk = (0.02 − |x̄ − 10.003|) / (3·s), i.e. theirs scaled by L/6; the t-test is the same.
    ours = type1(QT_TYPE1, tol, 10.003)
    s = float(np.std(QT_TYPE1, ddof=1))
    assert ours.cg == pytest.approx(0.2 * tol / (6 * s), rel=1e-12)
    assert ours.cg == pytest.approx(theirs.cg * their_spread / 6.0, rel=1e-12)
    assert ours.cgk == pytest.approx((theirs.cgk or 0) * their_spread / 6.0, rel=1e-12)
    assert (round(ours.cg, 2), round(ours.cgk or 0, 2)) == (1.00, 0.84)
    assert ours.t == theirs.t and ours.p == theirs.p
    assert not ours.capable and not theirs.capable  # Cg < 1.33 in either convention


def test_type1_by_hand() -> None:
    # x = 9.9 10.0 10.1 10.0 10.0: x̄ = 10, s = √0.005; T = 2, xm = 9.95
    # Cg = 0.2·2 / (6·√0.005) = 0.942809; Cgk = (0.1·2 − 0.05) / (3·√0.005) = 0.707107
    # t = 0.05 / (√0.005 / √5) = 1.581139 (4 dof); %Var = 20 / Cg = 21.2132 %
    res = type1([9.9, 10.0, 10.1, 10.0, 10.0], 2.0, 9.95, options=Type1Options(min_n=5))
    assert res.cg == pytest.approx(0.4 / (6 * math.sqrt(0.005)), rel=1e-12)
    assert round(res.cg, 6) == 0.942809
    assert round(res.cgk or 0, 6) == 0.707107
    assert round(res.t or 0, 6) == 1.581139
    assert res.p == pytest.approx(2 * stats.t.sf(1.581139, 4), abs=1e-6)
    assert res.bias_significant is False
    assert round(res.var_percent, 4) == 21.2132
    assert not res.capable


def test_type1_capable_and_without_reference() -> None:
    rng = np.random.default_rng(7)
    x = 0.3 + rng.normal(0, 0.01, 50)
    res = type1(x, 1.0, 0.3)
    assert res.cg == pytest.approx(0.2 / (6 * x.std(ddof=1)))
    assert res.capable and res.cgk is not None and res.cgk <= res.cg
    blind = type1(x, 1.0)
    assert blind.cgk is None and blind.bias is None and blind.cg == res.cg


def test_type1_refuses_what_it_cannot_judge() -> None:
    with pytest.raises(GaugeError, match="at least 25 measurements of one part, got 24"):
        type1(np.arange(24.0), 1.0, name="X")
    with pytest.raises(GaugeError, match="all 25 values are equal"):
        type1(np.ones(25), 1.0)
    with pytest.raises(GaugeError, match="X: value 3 is nan"):
        type1([1.0, 2.0, math.nan] * 9, 1.0, name="X")
    with pytest.raises(GaugeError, match="positive width"):
        type1(np.arange(25.0), 0.0)


def test_type3_by_hand() -> None:
    # parts [1, 3] and [5, 7]: means 2, 6, grand 4; SS_p = 2·(4 + 4) = 16 (1 dof),
    # SS_e = 4 (2 dof): MS_e = 2, EV = √2; PV = √((16 − 2)/2) = √7; TV = 3;
    # %GRR of TV = 100·√2/3 = 47.1405; ndc = floor(1.41·√7/√2) = floor(2.6378) = 2;
    # F = 8 on (1, 2): p = 1 − √8/√10 = 0.105573; %GRR of T = 4 is 100·6·√2/4 = 212.1320
    res = type3([[1.0, 3.0], [5.0, 7.0]], 4.0)
    assert res.ev == pytest.approx(math.sqrt(2)) and res.grr == res.ev
    assert res.pv == pytest.approx(math.sqrt(7))
    assert res.tv == pytest.approx(3.0)
    assert round(res.grr_tv_percent, 4) == 47.1405
    assert round(res.grr_tol_percent or 0, 4) == 212.1320
    assert res.ndc == 2
    assert round(res.p, 6) == 0.105573
    assert res.verdict == "not acceptable"


def test_type3_anova_agrees_with_scipy() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(0, 1.0, (10, 1)) + rng.normal(0, 0.05, (10, 3))
    res = type3(x, 20.0)
    f, p = stats.f_oneway(*x)
    assert res.f == pytest.approx(f, rel=1e-10) and res.p == pytest.approx(p, rel=1e-6)
    assert res.ndc >= 5 and res.verdict == "acceptable"


def test_type3_refuses_what_it_cannot_judge() -> None:
    with pytest.raises(GaugeError, match="at least 2 parts × 2 repeats, got 1 × 3"):
        type3([[1.0, 2.0, 3.0]])
    with pytest.raises(GaugeError, match="resolution is too coarse"):
        type3([[1.0, 1.0], [2.0, 2.0]])


# qualityTools vignette, section 3.2: response(design) of gageRRDesign(Operators=3, Parts=10,
# Measurements=2, randomize=FALSE), in the design's standard order: the operator changes fastest,
# then the part, then the measurement (so the table printed below is reproduced).
QT_GAGE_RR = [23, 22, 22, 22, 22, 25, 23, 22, 23, 22, 20, 22, 22, 22, 24, 25, 27, 28,
              23, 24, 23, 24, 24, 22, 22, 22, 24, 23, 22, 24, 20, 20, 25, 24, 22, 24, 21, 20,
              21, 22, 21, 22, 21, 21, 24, 27, 25, 27, 23, 22, 25, 23, 23, 22, 22, 23, 25, 21,
              24, 23]


def _qt_gage_rr() -> np.ndarray:
    """The vignette's readings as [part, operator, measurement]."""
    return np.asarray(QT_GAGE_RR, float).reshape(2, 10, 3).transpose(1, 2, 0)


def test_crossed_anova_matches_the_qualitytools_vignette_gage_rr_to_its_printed_digits() -> None:
    res = crossed_anova(_qt_gage_rr())
    assert (res.n_parts, res.appraisers, res.trials) == (10, 3, 2)
    op, part, inter, rep = res.table
    assert [t.source for t in res.table] == ["appraiser", "part", "part × appraiser",
                                             "repeatability"]
    # "Operator 2 20.63 10.317 8.597 0.00112 **"
    assert (op.df, round(op.ss, 2), round(op.ms, 3), round(op.f or 0, 3),
            round(op.p or 0, 5)) == (2, 20.63, 10.317, 8.597, 0.00112)
    # "Part 9 107.07 11.896 9.914 7.31e-07 ***"
    assert (part.df, round(part.ss, 2), round(part.ms, 3), round(part.f or 0, 3),
            f"{part.p:.2e}") == (9, 107.07, 11.896, 9.914, "7.31e-07")
    # "Operator:Part 18 22.03 1.224 1.020 0.46732"
    assert (inter.df, round(inter.ss, 2), round(inter.ms, 3), round(inter.f or 0, 3),
            round(inter.p or 0, 5)) == (18, 22.03, 1.224, 1.020, 0.46732)
    # "Residuals 30 36.00 1.200"
    assert (rep.df, round(rep.ss, 2), round(rep.ms, 3)) == (30, 36.00, 1.200)
    # "an interaction between parts and operators is not existing": p 0.467 ≥ 0.25, pooled
    assert res.pooled and res.pool_alpha == 0.25 and res.var_interaction == 0.0
    pooled = res.term("repeatability", reduced=True)
    assert pooled.df == 48 and pooled.ss == pytest.approx(22.0333 + 36.0, abs=1e-4)
    # "1.664 is the sum of 1.209 (repeatability ...) and 0.455 (reproducibility) ... Part to
    # Part amounts to 1.781 ... σ²_Total = 3.446"
    assert round(res.var_grr, 3) == 1.664
    assert round(res.var_repeatability, 3) == 1.209
    assert round(res.var_reproducibility, 3) == 0.455
    assert round(res.var_appraiser, 3) == 0.455
    assert round(res.var_part, 3) == 1.781
    assert round(res.var_total, 3) == 3.446
    # "48% of the variance is due to 35% repeatability ... and 13% reproducibility", "The
    # remaining 52% (51.7 in column VarCompContrib) ... stems from differences between parts"
    assert round(res.contribution("grr")) == 48
    assert round(res.contribution("repeatability")) == 35
    assert round(res.contribution("reproducibility")) == 13
    assert round(res.contribution("part")) == 52 and round(res.contribution("part"), 1) == 51.7
    # Not printed in the vignette, ours from the components above: %Study Var of GRR is
    # 100·√(1.6644/3.4456) = 69.50 %, ndc = floor(1.41·√(1.7812/1.6644)) = floor(1.459) = 1.
    assert round(res.study_var("grr"), 2) == 69.50
    assert res.ndc == 1 and res.verdict == "not acceptable"
    assert res.tolerance_percent("grr") is None
    t = crossed_anova(_qt_gage_rr(), 20.0)
    assert t.tolerance_percent("grr") == pytest.approx(100 * 6 * math.sqrt(t.var_grr) / 20)


def test_type3_is_the_one_appraiser_case_of_the_crossed_anova() -> None:
    xa = _qt_gage_rr()[:, 0, :]  # operator A alone: 10 parts × 2
    one = crossed_anova(xa[:, None, :], 5.0)
    assert [t.source for t in one.table] == ["part", "repeatability"] and not one.pooled
    assert one.var_appraiser == one.var_interaction == one.var_reproducibility == 0.0
    res = type3(xa, 5.0)
    assert (res.ms_parts, res.ms_error, res.f, res.p) == (
        one.term("part").ms, one.term("repeatability").ms, one.term("part").f,
        one.term("part").p)
    assert (res.ev, res.pv, res.ndc) == (one.sd("grr"), one.sd("part"), one.ndc)
    assert res.grr_tol_percent == one.tolerance_percent("grr")
    f, p = stats.f_oneway(*xa)  # scipy's one-way ANOVA, computed independently
    assert res.f == pytest.approx(f, rel=1e-12) and res.p == pytest.approx(p, rel=1e-9)


def _rss(y: np.ndarray, *factors: np.ndarray) -> float:
    """Residual sum of squares of y on the dummy columns of the given factor codes."""
    cols = [np.ones_like(y)] + [(f == v).astype(float) for f in factors for v in np.unique(f)]
    design = np.column_stack(cols)
    beta = np.linalg.lstsq(design, y, rcond=None)[0]
    return float(np.sum((y - design @ beta) ** 2))


def test_crossed_anova_keeps_a_significant_interaction() -> None:
    rng = np.random.default_rng(11)
    n, a, r = 8, 3, 3
    x = (rng.normal(0, 1.0, (n, 1, 1)) + rng.normal(0, 0.3, (1, a, 1))
         + rng.normal(0, 0.4, (n, a, 1)) + rng.normal(0, 0.1, (n, a, r)))
    res = crossed_anova(x, pool_alpha=0.25)
    app, part, inter, rep = res.table
    assert not res.pooled and (inter.p or 1) < 0.25
    # The sums of squares as differences of nested least-squares fits (balanced design).
    y = x.reshape(-1)
    pi, ai, _ = np.meshgrid(np.arange(n), np.arange(a), np.arange(r), indexing="ij")
    pi, ai = pi.reshape(-1), ai.reshape(-1)
    cell = pi * a + ai
    assert rep.ss == pytest.approx(_rss(y, cell), rel=1e-9)
    assert inter.ss == pytest.approx(_rss(y, pi, ai) - _rss(y, cell), rel=1e-9)
    assert app.ss == pytest.approx(_rss(y, pi) - _rss(y, pi, ai), rel=1e-9)
    assert part.ss == pytest.approx(_rss(y, ai) - _rss(y, pi, ai), rel=1e-9)
    # AIAG's components with the interaction kept: main effects over MS_pa, not MS_e.
    assert res.var_interaction == pytest.approx((inter.ms - rep.ms) / r)
    assert res.var_appraiser == pytest.approx(max(0.0, (app.ms - inter.ms) / (n * r)))
    assert res.var_part == pytest.approx((part.ms - inter.ms) / (a * r))
    assert res.var_repeatability == rep.ms
    # Pooled when its p ≥ pool_alpha: a level at half its p pools it, then MS_e is the pooled one.
    lax = crossed_anova(x, pool_alpha=(inter.p or 0) / 2)
    assert lax.pooled and lax.var_interaction == 0.0
    pooled_ms = (inter.ss + rep.ss) / (inter.df + rep.df)
    assert lax.var_repeatability == pytest.approx(pooled_ms, rel=1e-12)
    assert lax.var_part == pytest.approx((part.ms - pooled_ms) / (a * r), rel=1e-12)
    assert lax.term("part", reduced=True).f == pytest.approx(part.ms / pooled_ms, rel=1e-12)


def test_crossed_anova_refuses_what_it_cannot_judge() -> None:
    with pytest.raises(GaugeError, match=r"X: expected values \[parts, appraisers, trials\]"):
        crossed_anova(np.ones((3, 2)), name="X")
    with pytest.raises(GaugeError, match="2 parts × 1 appraiser × 2 trials, got 5 × 3 × 1"):
        crossed_anova(np.ones((5, 3, 1)))
    bad = _qt_gage_rr()
    bad[4, 1, 0] = math.nan
    with pytest.raises(GaugeError, match="X: part 5, appraiser 2, trial 1 is nan"):
        crossed_anova(bad, name="X")
    with pytest.raises(GaugeError, match="positive width"):
        crossed_anova(_qt_gage_rr(), -1.0)
    with pytest.raises(GaugeError, match="pool_alpha is a probability, got 25"):
        crossed_anova(_qt_gage_rr(), pool_alpha=25)
    with pytest.raises(KeyError, match="no ANOVA row 'operator'"):
        crossed_anova(_qt_gage_rr()).term("operator")
