"""Statistical process control: I-MR and X̄-R control limits, the Nelson run rules (and which
of them are the Western Electric rules), Cp/Cpk and Pp/Ppk. numpy only, no I/O.

Conventions (Montgomery, *Introduction to Statistical Quality Control*, ch. 6 and 8; NIST/SEMATECH
e-Handbook of Statistical Methods, sections 6.1.6, 6.3.2.1 and 6.3.2.2):

- σ **within** is estimated from ranges: MR̄/d2 (moving ranges of two, d2 = 1.128) or R̄/d2(n).
  Control limits and Cp/Cpk use it: they describe what the process does over a short time.
- σ **overall** is the sample standard deviation of all the values (ddof 1). Pp/Ppk use it: they
  describe what the parts were, drifts included.
- I-chart limits are X̄ ± 3·MR̄/d2 (= X̄ ± 2.66·MR̄, 2.66 being 3/1.128 rounded); the MR chart's
  upper limit is D4·MR̄ = 3.267·MR̄ and its lower limit 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray


class Factors(NamedTuple):
    """Control chart constants for subgroups of n (the standard table, e.g. Montgomery
    appendix VI; NIST 6.3.2.1): d2 = E[R]/σ, d3 = sd[R]/σ, A2 = 3/(d2·√n), D3 and D4 the R
    chart's limits over R̄ (D3 = max(0, 1 − 3·d3/d2), D4 = 1 + 3·d3/d2)."""

    d2: float
    d3: float
    A2: float
    D3: float
    D4: float


#: n → constants, n = 2..10, as printed in the standard table (3 decimals)
FACTORS: dict[int, Factors] = {
    2: Factors(1.128, 0.853, 1.880, 0.0, 3.267),
    3: Factors(1.693, 0.888, 1.023, 0.0, 2.574),
    4: Factors(2.059, 0.880, 0.729, 0.0, 2.282),
    5: Factors(2.326, 0.864, 0.577, 0.0, 2.114),
    6: Factors(2.534, 0.848, 0.483, 0.0, 2.004),
    7: Factors(2.704, 0.833, 0.419, 0.076, 1.924),
    8: Factors(2.847, 0.820, 0.373, 0.136, 1.864),
    9: Factors(2.970, 0.808, 0.337, 0.184, 1.816),
    10: Factors(3.078, 0.797, 0.308, 0.223, 1.777),
}


@dataclass(frozen=True)
class Limits:
    """Limits of a chart of values (individuals or subgroup means) and of its range chart."""

    center: float
    ucl: float
    lcl: float
    range_center: float  # MR̄ or R̄
    range_ucl: float
    range_lcl: float
    sigma_within: float  # MR̄/d2 or R̄/d2
    n: int  # values (I-MR) or subgroups (X̄-R) the limits come from


def _finite(values: ArrayLike, what: str) -> NDArray[np.float64]:
    x = np.asarray(values, dtype=float)
    if x.ndim != 1:
        raise ValueError(f"{what}: expected a 1-D series, got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise ValueError(f"{what}: value {bad} is {x[bad]} (not a finite number)")
    return x


def moving_ranges(values: ArrayLike) -> NDArray[np.float64]:
    """|x[i] − x[i−1]| for i = 1..n−1 (n − 1 values)."""
    x = _finite(values, "moving ranges")
    return np.abs(np.diff(x))


def imr_limits(values: ArrayLike) -> Limits:
    """Individuals and moving-range limits from a baseline of at least 2 values."""
    x = _finite(values, "I-MR baseline")
    if x.size < 2:
        raise ValueError(f"I-MR baseline: needs at least 2 values, got {x.size}")
    f = FACTORS[2]
    mr_bar = float(np.mean(np.abs(np.diff(x))))
    center = float(np.mean(x))
    sigma = mr_bar / f.d2
    return Limits(center, center + 3 * sigma, center - 3 * sigma, mr_bar, f.D4 * mr_bar,
                  f.D3 * mr_bar, sigma, int(x.size))


def xbar_r_limits(subgroups: ArrayLike) -> Limits:
    """X̄ and R limits from a baseline of subgroups, shape ``["m", "n"]``, n = 2..10."""
    g = np.asarray(subgroups, dtype=float)
    if g.ndim != 2 or g.shape[1] not in FACTORS or g.shape[0] < 1:
        raise ValueError(f"X̄-R baseline: expected m subgroups of n = 2..10 values (m × n), "
                         f"got shape {g.shape}")
    _finite(g.ravel(), "X̄-R baseline")
    f = FACTORS[g.shape[1]]
    xbarbar = float(np.mean(g))
    rbar = float(np.mean(np.ptp(g, axis=1)))
    return Limits(xbarbar, xbarbar + f.A2 * rbar, xbarbar - f.A2 * rbar, rbar, f.D4 * rbar,
                  f.D3 * rbar, rbar / f.d2, int(g.shape[0]))


# --------------------------------------------------------------------------- run rules
@dataclass(frozen=True)
class Rule:
    number: int
    name: str
    western_electric: bool  # one of the Western Electric Handbook's (1956) four zone rules


#: Nelson's eight rules (L. S. Nelson, "The Shewhart control chart — tests for special causes",
#: J. Quality Technology 16(4), 1984), σ being the chart's σ within. Rules 1, 5 and 6 are the
#: Western Electric rules 1-3; the fourth Western Electric rule is rule 2 with 8 points, not 9.
RULES: dict[int, Rule] = {r.number: r for r in (
    Rule(1, "1 point beyond 3σ", True),
    Rule(2, "9 points in a row on one side of the centre line", True),
    Rule(3, "6 points in a row steadily increasing or decreasing", False),
    Rule(4, "14 points in a row alternating up and down", False),
    Rule(5, "2 of 3 points in a row beyond 2σ on one side", True),
    Rule(6, "4 of 5 points in a row beyond 1σ on one side", True),
    Rule(7, "15 points in a row within 1σ of the centre line", False),
    Rule(8, "8 points in a row beyond 1σ, on either side", False),
)}


def _windows(flags: NDArray[np.bool_], length: int, need: int) -> NDArray[np.intp]:
    """Indices i where at least ``need`` of flags[i−length+1 .. i] are true."""
    if flags.size < length:
        return np.zeros(0, dtype=np.intp)
    c = np.concatenate([[0], np.cumsum(flags.astype(np.int64))])
    counts = c[length:] - c[:-length]
    return np.flatnonzero(counts >= need) + (length - 1)


def nelson(values: ArrayLike, center: float, sigma: float) -> dict[int, list[int]]:
    """Per Nelson rule (1-8), the indices of the points that complete its pattern (the last
    point of the run; a run longer than the rule's length flags each further point too)."""
    x = _finite(values, "run rules")
    if not (np.isfinite(center) and np.isfinite(sigma) and sigma >= 0):
        raise ValueError(f"run rules: centre {center} and σ {sigma} must be finite, σ ≥ 0")
    # σ = 0 (a constant baseline): any departure from the centre is beyond every zone, but not
    # the centre's own rounding (a mean of equal floats need not equal them to the last bit)
    dev = x - center
    dev[np.abs(dev) <= 1e-9 * max(1.0, abs(center))] = 0.0
    z = dev / sigma if sigma > 0 else np.where(dev > 0, np.inf, np.where(dev < 0, -np.inf, 0.0))
    up, down = z > 0, z < 0
    d = np.diff(x)
    rises, falls = d > 0, d < 0
    alt = (d[1:] * d[:-1]) < 0  # a turn at point i + 1
    out = {
        1: np.flatnonzero(np.abs(z) > 3),
        2: np.union1d(_windows(up, 9, 9), _windows(down, 9, 9)),
        3: np.union1d(_windows(rises, 5, 5), _windows(falls, 5, 5)) + 1,
        4: _windows(alt, 12, 12) + 2,
        5: np.union1d(_windows(z > 2, 3, 2), _windows(z < -2, 3, 2)),
        6: np.union1d(_windows(z > 1, 5, 4), _windows(z < -1, 5, 4)),
        # with σ = 0 there is no 1σ zone to be within (a constant series is not a stratified one)
        7: _windows(np.abs(z) < 1, 15, 15) if sigma > 0 else np.zeros(0, dtype=np.intp),
        8: _windows(np.abs(z) > 1, 8, 8),
    }
    return {k: [int(i) for i in v] for k, v in out.items()}


# --------------------------------------------------------------------------- capability
@dataclass(frozen=True)
class Capability:
    """Cp/Cpk with σ within, Pp/Ppk with σ overall; one-sided specifications have only the
    index of their side in Cpk/Ppk and no Cp/Pp (None)."""

    cp: float | None
    cpk: float | None
    pp: float | None
    ppk: float | None
    mean: float
    sigma_within: float
    sigma_overall: float
    n: int


def _indices(mean: float, sigma: float, lsl: float | None,
             usl: float | None) -> tuple[float | None, float | None]:
    if sigma <= 0 or not np.isfinite(sigma):
        return None, None
    sides = [(usl - mean) / (3 * sigma) if usl is not None else None,
             (mean - lsl) / (3 * sigma) if lsl is not None else None]
    p = (usl - lsl) / (6 * sigma) if usl is not None and lsl is not None else None
    return p, min(s for s in sides if s is not None)


def capability(values: ArrayLike, lsl: float | None, usl: float | None,
               sigma_within: float | None = None) -> Capability:
    """Capability of ``values`` against the specification [lsl, usl] (either may be None).

    σ within defaults to MR̄/d2 of the values themselves (pass R̄/d2 from an X̄-R baseline);
    σ overall is their sample standard deviation (ddof 1)."""
    x = _finite(values, "capability")
    if x.size < 2:
        raise ValueError(f"capability: needs at least 2 values, got {x.size}")
    if lsl is None and usl is None:
        raise ValueError("capability: needs a lower or an upper specification limit")
    if lsl is not None and usl is not None and not usl > lsl:
        raise ValueError(f"capability: upper limit {usl} is not above lower limit {lsl}")
    mean = float(np.mean(x))
    within = (float(np.mean(np.abs(np.diff(x)))) / FACTORS[2].d2
              if sigma_within is None else float(sigma_within))
    overall = float(np.std(x, ddof=1))
    cp, cpk = _indices(mean, within, lsl, usl)
    pp, ppk = _indices(mean, overall, lsl, usl)
    return Capability(cp, cpk, pp, ppk, mean, within, overall, int(x.size))
