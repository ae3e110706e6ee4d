"""The linearity study: every reading's bias regressed on its reference value (AIAG MSA)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from mvpose_core.gauge.base import GaugeError, clean
from mvpose_core.transforms import Array


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
    ref = clean(reference, f"{name} reference")
    y = clean(readings, name)
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
