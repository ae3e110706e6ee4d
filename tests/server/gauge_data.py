"""Stored measurements for gauge studies: parts measured again and again around a known offset."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from records import make_record

from mvpose_core.transforms import RobotConvention, from_robot
from server.store import Store
from server.store.schemas import MeasurementRecord, Offset

TRUE = (4.0, -2.5, 1.0, 0.05, -0.03, 0.2)  # a FANUC offset X Y Z W P R


def store_repeats(store: Store, rng: np.random.Generator, part_id: str, n: int,
                  true: Sequence[float] = TRUE, sigma_mm: float = 0.01,
                  sigma_deg: float = 0.001, first_trigger: int = 1) -> list[int]:
    """``n`` OK records of ``part_id`` whose offsets scatter around ``true``; their seqs."""
    seqs = []
    for i in range(n):
        noise = np.r_[rng.normal(0, sigma_mm, 3), rng.normal(0, sigma_deg, 3)]
        values = np.asarray(true) + noise
        T = from_robot(values, RobotConvention.FANUC)
        rec = make_record(rng, trigger_id=first_trigger + i, part_id=part_id)
        rec = rec.model_copy(update={
            "offset": Offset(convention=RobotConvention.FANUC, values=[float(v) for v in values]),
            "T_rf_from_pf": MeasurementRecord.matrix(T),
        })
        seqs.append(store.measurements.insert(rec).seq)
    return seqs
