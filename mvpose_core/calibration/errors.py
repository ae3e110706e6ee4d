"""The one exception calibration raises for input it cannot use; the message names the problem."""

from __future__ import annotations


class CalibrationError(ValueError):
    """Calibration input is degenerate or inconsistent (too few samples, wrong unit, ...)."""
