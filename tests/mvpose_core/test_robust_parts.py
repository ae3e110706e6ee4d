"""The robust rule's small parts give what the numpy and dataclass calls they replace gave."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from mvpose_core.problem import Observation
from mvpose_core.robust import _threshold


def test_the_threshold_takes_numpys_median() -> None:
    rng = np.random.default_rng(4)
    for n in range(1, 40):
        res = [rng.uniform(0.0, 1.0, int(rng.integers(1, 4))) for _ in range(n)]
        chosen = [int(rng.integers(len(r))) for r in res]
        used = rng.uniform(size=n) < 0.8
        lengths = [res[k][chosen[k]] for k in np.flatnonzero(used)]
        limit = 0.5
        expected = max(limit, 4.0 * float(np.median(lengths))) if lengths else limit
        assert _threshold(limit, res, chosen, used) == expected  # to the last bit
    # a NaN residual: np.median's NaN, which max() passes over
    res = [np.array([0.2]), np.array([np.nan]), np.array([0.3])]
    assert _threshold(0.5, res, [0, 0, 0], np.ones(3, dtype=bool)) == 0.5


def test_an_observation_changed_by_but_equals_dataclasses_replace() -> None:
    o = Observation(1, "left", "M1", np.array([1.0, 2.0]), alternates=(np.array([3.0, 4.0]),),
                    centre_variance=0.02)
    uv = np.array([5.0, 6.0])
    a, b = o.but(uv=uv, sigma_px=0.1), replace(o, uv=uv, sigma_px=0.1)
    assert a == b and a is not o and a.uv is uv and o.uv[0] == 1.0 and o.sigma_px is None
    assert type(a) is Observation and a.key == o.key
