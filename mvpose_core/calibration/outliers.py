"""Samples that stand out from the others: by reprojection RMS, or by their robot pose's misfit."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from scipy.stats import chi2


def find_outliers(
    per_sample: Mapping[str, float], factor: float = 4.0, min_excess_px: float = 0.1
) -> list[str]:
    """Samples whose RMS is far above the others: above median + ``factor``·(robust σ), above
    1.5× the median and at least ``min_excess_px`` above it (so differences at the level of
    detector noise are not flagged)."""
    if len(per_sample) < 4:
        return []
    v = np.array(list(per_sample.values()))
    med = float(np.median(v))
    mad = 1.4826 * float(np.median(np.abs(v - med)))
    limit = max(med + factor * mad, 1.5 * med, med + min_excess_px)
    return [sid for sid, x in per_sample.items() if x > limit]


def find_pose_outliers(chi2_per_sample: Mapping[str, float], p: float = 1e-3) -> list[str]:
    """Samples whose flange-pose correction (χ², 6 degrees of freedom) is beyond what the others
    allow: each χ² is scaled by the median's (robust against the outlier's own pull on the
    estimated robot σ) and compared with the χ² quantile at ``p`` shared over the samples."""
    if len(chi2_per_sample) < 5:
        return []
    v = np.array(list(chi2_per_sample.values()))
    scale = max(float(np.median(v)) / float(chi2.median(6)), 1e-300)
    limit = float(chi2.isf(p / len(v), 6))
    return [sid for sid, x in chi2_per_sample.items() if x / scale > limit]
