"""What every gauge study shares: the acceptance limits, the error, the input check."""

from __future__ import annotations

import numpy as np

from mvpose_core.transforms import Array

CAPABLE = 1.33  # Cg and Cgk a type-1 study needs (Booklet 10, VDA 5, AIAG)
GRR_ACCEPTABLE = 10.0  # %GRR at or below: acceptable (AIAG MSA 4th ed.)
GRR_CONDITIONAL = 30.0  # %GRR at or below: acceptable for some applications
NDC_MIN = 5  # distinct categories a type-3 study needs (AIAG MSA 4th ed.)
MIN_TYPE1 = 25  # repeats a type-1 study needs (Booklet 10: at least 25, better 50)


class GaugeError(ValueError):
    """The data cannot make the study; the message names the characteristic and what is wrong."""


def clean(values: Array | list[float], name: str) -> Array:
    """The values as a flat float array; a value that is not finite is refused by its place."""
    x = np.asarray(values, dtype=float).reshape(-1)
    if not np.all(np.isfinite(x)):
        bad = int(np.flatnonzero(~np.isfinite(x))[0])
        raise GaugeError(f"{name}: value {bad + 1} is {float(x[bad])!r}")
    return x
