"""SPC against published worked examples (their printed digits) and hand-derived series."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mvpose_core.spc import FACTORS, RULES, capability, imr_limits, nelson, xbar_r_limits

#: NIST/SEMATECH e-Handbook of Statistical Methods, 6.3.2.2 "Individuals control charts"
#: (https://www.itl.nist.gov/div898/handbook/pmc/section3/pmc322.htm): flow rate of 10 batches.
NIST_FLOW = [49.6, 47.6, 49.9, 51.3, 47.8, 51.2, 52.6, 52.4, 53.6, 52.1]


def test_imr_limits_match_the_nist_individuals_example() -> None:
    """NIST e-Handbook 6.3.2.2 prints x̄ = 50.81, MR̄ = 1.8778, UCL = 55.8041, LCL = 45.8159
    (x̄ ± 3·MR̄/1.128). The handbook's page itself could not be opened from here; its data and
    digits are as quoted, identically, by several independent public test suites. The MR
    chart's UCL is checked against D4·MR̄ = 3.267·MR̄ (its printed digits were not read)."""
    lim = imr_limits(NIST_FLOW)
    assert round(lim.center, 2) == 50.81
    assert round(lim.range_center, 4) == 1.8778
    assert round(lim.ucl, 4) == 55.8041
    assert round(lim.lcl, 4) == 45.8159
    assert lim.range_ucl == pytest.approx(3.267 * 16.9 / 9)
    assert lim.range_lcl == 0.0 and lim.n == 10
    assert lim.sigma_within == pytest.approx((16.9 / 9) / 1.128)
    # 2.66·MR̄ is the same limit to the 3 decimals of the factor
    assert lim.ucl - lim.center == pytest.approx(2.66 * lim.range_center, rel=1e-3)
    # no point of the example is out of control (NIST: "the process is in control")
    assert nelson(NIST_FLOW, lim.center, lim.sigma_within)[1] == []


def test_the_factor_table_agrees_with_its_definitions() -> None:
    """The A2, D3, D4 printed in the standard table (Montgomery, Appendix VI; NIST 6.3.2.1)
    follow from d2 and d3 to the table's 3 decimals: A2 = 3/(d2√n), D4 = 1 + 3·d3/d2,
    D3 = max(0, 1 − 3·d3/d2)."""
    for n, f in FACTORS.items():
        assert abs(f.A2 - 3 / (f.d2 * math.sqrt(n))) < 1.5e-3, n
        assert abs(f.D4 - (1 + 3 * f.d3 / f.d2)) < 2e-3, n
        assert abs(f.D3 - max(0.0, 1 - 3 * f.d3 / f.d2)) < 2e-3, n
    assert FACTORS[5] == (2.326, 0.864, 0.577, 0.0, 2.114)


def test_xbar_r_limits_on_a_hand_derived_example() -> None:
    """Hand-derived (no published data set with its printed limits could be read here): three
    subgroups of 5 with means 10, 11, 12 and ranges 2, 4, 3 → X̿ = 11, R̄ = 3, UCL = 11 +
    0.577·3 = 12.731, LCL = 9.269, UCL_R = 2.114·3 = 6.342, LCL_R = 0, σ within = 3/2.326."""
    g = [[9, 10, 10, 10, 11], [9, 11, 11, 11, 13], [10.5, 12, 12, 12, 13.5]]
    lim = xbar_r_limits(g)
    assert lim.center == pytest.approx(11.0) and lim.range_center == pytest.approx(3.0)
    assert lim.ucl == pytest.approx(12.731) and lim.lcl == pytest.approx(9.269)
    assert lim.range_ucl == pytest.approx(6.342) and lim.range_lcl == 0.0
    assert lim.sigma_within == pytest.approx(3 / 2.326) and lim.n == 3
    # n = 7 has a lower range limit
    g7 = np.tile(np.arange(7.0), (4, 1))
    assert xbar_r_limits(g7).range_lcl == pytest.approx(0.076 * 6)


def test_capability_matches_the_nist_example() -> None:
    """NIST e-Handbook 6.1.6 "What is process capability?": USL 20, LSL 8, μ 16, σ 2 →
    Cp = 1.0, Cpk = 0.6667 (Cpu 0.6667, Cpl 1.3333). The data here are constructed to have
    mean 16 and standard deviation 2 exactly, so Pp/Ppk equal Cp/Cpk with σ within = 2."""
    z = np.random.default_rng(1).normal(size=100)
    x = 16 + 2 * (z - z.mean()) / z.std(ddof=1)
    c = capability(x, lsl=8, usl=20, sigma_within=2.0)
    assert c.cp is not None and c.cpk is not None and c.pp is not None and c.ppk is not None
    assert round(c.cp, 4) == 1.0 and round(c.cpk, 4) == 0.6667
    assert round(c.pp, 4) == 1.0 and round(c.ppk, 4) == 0.6667
    # one-sided (an upper limit only, as for a residual): Cpu only, no Cp
    up = capability(x, lsl=None, usl=20, sigma_within=2.0)
    assert up.cp is None and up.cpk == pytest.approx(4 / 6)
    low = capability(x, lsl=8, usl=None, sigma_within=2.0)
    assert low.cpk == pytest.approx(8 / 6)


def test_capability_within_comes_from_moving_ranges_and_overall_from_the_sample() -> None:
    c = capability(NIST_FLOW, lsl=45, usl=57)
    assert c.sigma_within == pytest.approx((16.9 / 9) / 1.128)
    assert c.sigma_overall == pytest.approx(float(np.std(NIST_FLOW, ddof=1)))
    assert c.cp == pytest.approx(12 / (6 * c.sigma_within))
    assert c.ppk == pytest.approx(min(57 - c.mean, c.mean - 45) / (3 * c.sigma_overall))


@pytest.mark.parametrize("rule, series, expected", [
    # hand-derived, centre 0 and σ 1
    (1, [0, 0.5, 3.5, 0, -3.2], [2, 4]),
    (2, [0.1] * 9 + [-0.1] * 3, [8]),
    (2, [-0.2] * 10, [8, 9]),
    (3, [0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.4], [5]),
    (3, [0.5, 0.4, 0.3, 0.2, 0.1, 0.0, -0.1], [5, 6]),
    (4, [0.1, -0.1] * 7, [13]),
    (5, [0, 2.5, 0, 2.2, 0], [3]),
    (5, [0, 2.5, 0, -2.2, 0], []),  # different sides
    (6, [1.5, 1.2, 0, 1.1, 1.3, 0], [4]),  # the window ending at 5 has 3
    (7, [0.5, -0.5] * 8, [14, 15]),
    (8, [1.5, -1.5] * 4, [7]),
])
def test_each_nelson_rule_flags_the_point_that_completes_it(
    rule: int, series: list[float], expected: list[int],
) -> None:
    assert nelson(series, 0.0, 1.0)[rule] == expected


def test_rules_are_named_and_the_western_electric_ones_marked() -> None:
    assert sorted(RULES) == list(range(1, 9))
    assert [r.number for r in RULES.values() if r.western_electric] == [1, 2, 5, 6]
    flags = nelson([0.0, 0.1, -0.1], 0.0, 1.0)
    assert sorted(flags) == list(range(1, 9)) and not any(flags.values())


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="at least 2 values, got 1"):
        imr_limits([1.0])
    with pytest.raises(ValueError, match=r"value 1 is nan"):
        imr_limits([1.0, float("nan")])
    with pytest.raises(ValueError, match=r"n = 2\.\.10 .*shape \(2, 11\)"):
        xbar_r_limits(np.zeros((2, 11)))
    with pytest.raises(ValueError, match="upper limit 1 is not above lower limit 2"):
        capability([1.0, 2.0], lsl=2, usl=1)


def test_a_constant_baseline_flags_any_departure() -> None:
    lim = imr_limits([1.0, 1.0, 1.0])
    assert lim.sigma_within == 0.0 and lim.ucl == lim.lcl == 1.0
    assert nelson([1.0, 1.0, 1.2, 1.0], lim.center, lim.sigma_within)[1] == [2]
    # a mean of equal values that misses them in the last bit is still their centre
    same = [-8.27] * 7
    centre = float(np.mean(same))
    assert nelson(same, centre, 0.0)[1] == [] and nelson(same, centre + 1e-14, 0.0)[1] == []
    assert not any(nelson([2.0] * 20, 2.0, 0.0).values())  # no zones: no rule 7 either
    assert capability([1.0, 1.0, 1.0], lsl=0, usl=2).cpk is None  # no spread: no index
