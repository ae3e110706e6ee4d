"""Quality gate: OK or NOK with a stable reason code (the number goes to the PLC and the audit).

The codes never change meaning; new reasons get new numbers. Checks run in the order below and
the first failing one is reported (the most basic cause first: a missing mark explains a high
uncertainty, not the other way round).

====  ==============================  ====================================================
code  name                            NOK when
====  ==============================  ====================================================
0     OK                              every check passed
1     MARKS_MISSING                   fewer marks observed than ``tolerances.min_marks``
2     NOT_CONVERGED                   the solver stopped without converging
3     RESIDUAL_RMS_HIGH               RMS reprojection error > ``tolerances.max_rms_px``
4     RESIDUAL_MAX_HIGH               one residual > ``tolerances.max_residual_px``
5     ROTATION_UNCERTAINTY_HIGH       1σ rotation at the grasp > ``tolerances.rotation_deg``
6     TRANSLATION_UNCERTAINTY_HIGH    1σ translation at the grasp > ``tolerances.translation_mm``
7     OFFSET_TRANSLATION_OUT_OF_RANGE grasp point moved more than ``tolerances.max_offset_mm``
8     OFFSET_ROTATION_OUT_OF_RANGE    part rotated more than ``tolerances.max_offset_deg``
9     BAD_INPUT                       the estimator refused its input (NaN, shapes, layout …)
10    TOO_FEW_MARKS                   fewer than 3 marks: no pose can be computed at all
11    POSE_NOT_DETERMINED             the observations leave a degree of freedom open
12    MARK_BEHIND_CAMERA              the pose puts an observed mark behind its camera
====  ==============================  ====================================================

The uncertainty checks judge the 1σ of :mod:`mvpose_core.measure`: the detector part at the
noise the residuals show (so a bad detection cannot hide behind a good noise model) plus the
calibration part (docs/engine.md, "Uncertainty model").
"""

from __future__ import annotations

from dataclasses import dataclass

from mvpose_core.reasons import Reason
from mvpose_core.station import Tolerances


@dataclass(frozen=True)
class GateVerdict:
    """OK/NOK, the reason code and a one-line message naming the value and the limit."""

    ok: bool
    reason: Reason
    message: str


@dataclass(frozen=True)
class GateInputs:
    """The figures the gate judges (all plain numbers, so the gate is testable on its own)."""

    marks_used: int
    converged: bool
    termination: str
    rms_px: float
    max_residual_px: float
    sigma_rot_deg: float
    sigma_trans_mm: float
    offset_mm: float
    offset_deg: float
    missing: tuple[str, ...] = ()


def evaluate_gate(x: GateInputs, tol: Tolerances, min_marks: int) -> GateVerdict:
    """Judge one measurement against a recipe's tolerances."""
    if x.marks_used < min_marks:
        shown = ", ".join(x.missing) if x.missing else "?"
        return _nok(
            Reason.MARKS_MISSING,
            f"{x.marks_used} marks found, recipe needs {min_marks} (missing: {shown})",
        )
    if not x.converged:
        return _nok(Reason.NOT_CONVERGED, f"solver did not converge ({x.termination})")
    checks = [
        (Reason.RESIDUAL_RMS_HIGH, "RMS reprojection error", x.rms_px, tol.max_rms_px, "px"),
        (
            Reason.RESIDUAL_MAX_HIGH,
            "largest residual",
            x.max_residual_px,
            tol.max_residual_px,
            "px",
        ),
        (
            Reason.ROTATION_UNCERTAINTY_HIGH,
            "1σ rotation at the grasp",
            x.sigma_rot_deg,
            tol.rotation_deg,
            "°",
        ),
        (
            Reason.TRANSLATION_UNCERTAINTY_HIGH,
            "1σ translation at the grasp",
            x.sigma_trans_mm,
            tol.translation_mm,
            "mm",
        ),
        (
            Reason.OFFSET_TRANSLATION_OUT_OF_RANGE,
            "grasp point offset",
            x.offset_mm,
            tol.max_offset_mm,
            "mm",
        ),
        (
            Reason.OFFSET_ROTATION_OUT_OF_RANGE,
            "rotation offset",
            x.offset_deg,
            tol.max_offset_deg,
            "°",
        ),
    ]
    for code, what, value, limit, unit in checks:
        if not value <= limit:  # NaN fails too
            return _nok(code, f"{what} {value:.3f} {unit} exceeds {limit:g} {unit}")
    return GateVerdict(True, Reason.OK, "OK")


def _nok(code: Reason, message: str) -> GateVerdict:
    return GateVerdict(False, code, message)
