"""The gauge formulas against published worked examples (linearity, type 1) and hand-derived
ones (type 3).

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

No published no-operator type-3 example with its data and ANOVA results could be read here; the
type-3 formulas are tested against values derived by hand below (closed forms in the comments)
and against scipy's independent one-way ANOVA.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from mvpose_core.gauge import GaugeError, Type1Options, linearity, type1, type3

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
