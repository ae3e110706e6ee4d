"""The drift watch's history: what it keeps to date a drift and measure the move since.

Per camera, the station trigger index and the running sums of its updates (:class:`History`),
and per trigger its time stamp (:class:`Stamps`): numpy rings of exactly the watch's
``DriftOptions.history`` entries, so the memory a watch takes is bounded and small
(:func:`history_bytes`; docs/calibration.md, "Drift watch").
"""

from __future__ import annotations

import math

import numpy as np

from mvpose_core.transforms import Array


class History:
    """The last ``size`` updates of one camera: trigger index and cumulative sums, in a ring.

    Entry ``i`` is the station trigger index of an update and Σ (x − μ, in-fit fraction) ``[3]``
    up to and including it; ``floor`` holds the sums before the oldest kept entry (those of the
    last one dropped). Numpy arrays of exactly ``size`` entries: 32 bytes an update, where a list
    of ints and a list of tuples of floats took ~145. The arrays are allocated at once, zeroed
    (their pages reach the resident memory as they are first written).
    """

    def __init__(self, size: int, start: int) -> None:
        self.idx = np.zeros(size, dtype=np.int64)
        self.cum = np.zeros((size, 3))
        self.n = 0  # entries kept (≤ size)
        self.head = 0  # position of the oldest entry once full; the next written one
        self.floor_at = start  # trigger index of the floor (the last dropped or the start)
        self.floor = (0.0, 0.0, 0.0)
        self.last = (0.0, 0.0, 0.0)  # the newest sums, as floats (fed back each update)

    def append(self, n: int, du: float, dv: float, in_fit: float) -> None:
        """Keep the update of trigger ``n`` (indices increase), dropping the oldest when full."""
        size = len(self.idx)
        a, b, c = self.last
        self.last = (a + du, b + dv, c + in_fit)
        if self.n < size:
            i = self.n
            self.n += 1
        else:
            i = self.head
            self.floor_at = int(self.idx[i])
            self.floor = (float(self.cum[i, 0]), float(self.cum[i, 1]), float(self.cum[i, 2]))
            self.head = (i + 1) % size
        self.idx[i] = n
        self.cum[i] = self.last

    def _at(self, j: int) -> int:
        """The array position of the ``j``-th oldest entry."""
        return (self.head + j) % len(self.idx)

    def since(self, n0: int) -> Array | None:
        """Means of ``(x − μ, in-fit fraction)`` ``[3]`` over the updates from trigger ``n0``
        (over all kept when ``n0`` is older than the oldest kept; None when none is that new)."""
        if self.n == 0 or self.idx[self._at(self.n - 1)] < n0:
            return None
        if self.n < len(self.idx) or self.head == 0:  # one sorted run
            j = int(np.searchsorted(self.idx[: self.n], n0))
        else:  # two sorted runs: the oldest from ``head``, then the newest from 0
            older = self.idx[self.head :]
            if older[-1] >= n0:
                j = int(np.searchsorted(older, n0))
            else:
                j = len(older) + int(np.searchsorted(self.idx[: self.head], n0))
        before = np.asarray(self.cum[self._at(j - 1)] if j > 0 else self.floor)
        return (np.asarray(self.last) - before) / (self.n - j)

    @property
    def nbytes(self) -> int:
        return int(self.idx.nbytes + self.cum.nbytes)


class Stamps:
    """The time stamps of the last ``size`` triggers (epoch seconds, NaN for none), in a ring."""

    def __init__(self, size: int) -> None:
        self.t = np.full(size, np.nan)
        self.n = 0  # triggers stamped so far

    def append(self, stamp: float | None) -> None:
        self.t[self.n % len(self.t)] = np.nan if stamp is None else stamp
        self.n += 1

    def get(self, i: int) -> float | None:
        """Trigger ``i``'s stamp, None when it had none or is no longer kept."""
        if not self.n - len(self.t) <= i < self.n or i < 0:
            return None
        t = float(self.t[i % len(self.t)])
        return None if math.isnan(t) else t


#: bytes a trigger adds to a drift watch's history: a camera's update and the trigger's stamp
HISTORY_BYTES_PER_CAMERA = 32
HISTORY_BYTES_PER_TRIGGER = 8


def history_bytes(cameras: int, history: int) -> int:
    """The drift watch's history at its cap: ``history`` triggers of ``cameras`` cameras."""
    return history * (cameras * HISTORY_BYTES_PER_CAMERA + HISTORY_BYTES_PER_TRIGGER)
