"""The type-1 study: one part measured n ≥ 25 times; Cg, Cgk and the bias's significance."""

from __future__ import annotations

import math
from dataclasses import dataclass

from scipy import stats

from mvpose_core.gauge.base import CAPABLE, MIN_TYPE1, GaugeError, clean
from mvpose_core.transforms import Array


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


def type1(values: Array | list[float], tolerance: float, reference: float | None = None, *,
          name: str = "x", unit: str = "", options: Type1Options | None = None) -> Type1Result:
    """A type-1 study of one characteristic: one part measured ``n ≥ 25`` times.

    ``tolerance`` is the full width T = USL − LSL; ``reference`` is the part's reference value
    xm (None: unknown, no bias and no Cgk).
    """
    opt = options or Type1Options()
    x = clean(values, name)
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
