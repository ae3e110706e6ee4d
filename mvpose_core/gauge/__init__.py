"""Gauge capability studies on arrays: type 1 (Cg, Cgk, bias), the crossed gauge R&R ANOVA and its
one-appraiser case type 3 (%GRR, ndc), and linearity (bias regressed on the reference value).
No I/O; docs/gauge.md has the sources.

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
- Crossed gauge R&R (n parts × a appraisers × r trials): AIAG *Measurement Systems Analysis*,
  4th edition (2010), the ANOVA method (VDA 5 / Booklet 10 procedure 2 is the same model): a
  two-way ANOVA with interaction, AIAG's variance components, %Contribution, %Study Var,
  %Tolerance, ``ndc = floor(1.41 · PV / GRR)``. The interaction is pooled into repeatability when
  its p ≥ 0.25 or its component is negative (the rule of qualityTools' ``gageRR``,
  alpha = 0.25). Published example: Roth's qualityTools vignette (above), section 3.2 "Gage
  Repeatability&Reproducibility - MSA Type II", 10 parts × 3 operators × 2: its printed ANOVA
  table (Df, SS, MS, F, p of each term), variance components (1.209, 0.455, 1.664, 1.781, 3.446)
  and contributions (35 %, 13 %, 48 %, 51.7 %) are reproduced to their digits by
  ``crossed_anova`` (tests/mvpose_core/test_gauge.py).
- Type 3 (no operator influence, Booklet 10 procedure 3): the one-appraiser case of the crossed
  ANOVA, computed by ``crossed_anova`` (a one-way ANOVA of parts × repeats: EV = GRR, PV from
  the between-part mean square). Spreads are 6σ (the 4th edition and Booklet 10; the 3rd edition
  used 5.15σ). No published no-operator example with its data and ANOVA results could be read.
- Linearity: AIAG MSA 4th edition, Chapter III Section B, the linearity study: every reading's
  bias regressed on its reference value by least squares; slope and intercept tested with t on
  g·m − 2 degrees of freedom. The manual's worked example (5 parts × 12 readings at 2, 4, 6, 8,
  10) gives slope −0.1317, intercept 0.7367, R² 0.71 (tests/mvpose_core/test_gauge.py).
"""

from mvpose_core.gauge.anova import (
    POOL_ALPHA,
    AnovaTerm,
    CrossedAnova,
    Type3Result,
    crossed_anova,
    type3,
)
from mvpose_core.gauge.base import (
    CAPABLE,
    GRR_ACCEPTABLE,
    GRR_CONDITIONAL,
    MIN_TYPE1,
    NDC_MIN,
    GaugeError,
)
from mvpose_core.gauge.linearity import LinearityResult, linearity
from mvpose_core.gauge.type1 import Type1Options, Type1Result, type1

__all__ = [
    "CAPABLE", "GRR_ACCEPTABLE", "GRR_CONDITIONAL", "MIN_TYPE1", "NDC_MIN", "POOL_ALPHA",
    "AnovaTerm", "CrossedAnova", "GaugeError", "LinearityResult", "Type1Options", "Type1Result",
    "Type3Result", "crossed_anova", "linearity", "type1", "type3",
]
