"""The drift watch's history as it was kept before it became numpy rings (commit d56f593): lists
of Python ints and tuples, trimmed to ``history`` entries once they pass twice as many.

:class:`ListDriftWatch` is :class:`mvpose_core.drift.DriftWatch` with that storage in place of
:mod:`mvpose_core.drift_history`'s rings (the CUSUM, the dating and the explanation are the
watch's own). Kept only for tests/mvpose_core/test_drift_history.py, which runs both side by
side and asks them the same questions.
"""

from __future__ import annotations

from bisect import bisect_left
from collections.abc import Mapping

import numpy as np

from mvpose_core.drift import CameraKey, DriftOptions, DriftWatch, _Camera
from mvpose_core.transforms import Array


class ListHistory:
    """A camera's updates as lists: trigger indices and cumulative sums ``[3]`` after each;
    past ``2 × size`` entries the oldest are dropped down to ``size`` (``floor``: the sums of the
    last one dropped)."""

    def __init__(self, size: int, start: int) -> None:
        self.size = size
        self.idx: list[int] = []
        self.cum: list[tuple[float, float, float]] = []
        self.floor_at = start
        self.floor = (0.0, 0.0, 0.0)

    def append(self, n: int, du: float, dv: float, in_fit: float) -> None:
        a, b, c = self.cum[-1] if self.cum else self.floor
        self.idx.append(n)
        self.cum.append((a + du, b + dv, c + in_fit))
        if len(self.idx) > 2 * self.size:
            cut = len(self.idx) - self.size
            self.floor_at, self.floor = self.idx[cut - 1], self.cum[cut - 1]
            del self.idx[:cut], self.cum[:cut]

    def since(self, n0: int) -> Array | None:
        if not self.idx or self.idx[-1] < n0:
            return None
        j = bisect_left(self.idx, n0)
        before = np.asarray(self.cum[j - 1] if j > 0 else self.floor)
        return (np.asarray(self.cum[-1]) - before) / (len(self.idx) - j)


class ListStamps:
    """Each trigger's stamp in a dict, trimmed to the last ``size`` once past twice as many."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.t: dict[int, float | None] = {}
        self.n = 0

    def append(self, stamp: float | None) -> None:
        self.t[self.n] = stamp
        if len(self.t) > 2 * self.size:
            keep = self.n - self.size
            self.t = {i: s for i, s in self.t.items() if i >= keep}
        self.n += 1

    def get(self, i: int) -> float | None:
        return self.t.get(i)


class ListDriftWatch(DriftWatch):
    """The watch with the list storage (see the module docstring)."""

    def __init__(self, options: DriftOptions = DriftOptions(),  # noqa: B008 - frozen
                 response: Mapping[CameraKey, Mapping[CameraKey, Array]] | None = None) -> None:
        super().__init__(options, response)
        self._stamps = ListStamps(options.history)  # type: ignore[assignment]

    def _start(self, cam: _Camera, mu: Array, sd: Array) -> None:
        super()._start(cam, mu, sd)
        cam.history = ListHistory(self.options.history, self._n - 1)  # type: ignore[assignment]
