"""The drift watch as it was before its history became numpy rings (commit d56f593): lists of
Python ints and tuples, trimmed to ``history`` entries once they pass twice as many.

Kept only for tests/mvpose_core/test_drift_history.py, which runs it beside
:class:`mvpose_core.drift.DriftWatch` and asks both the same questions.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from mvpose_core.drift import CameraDrift, CameraKey, DriftOptions, Response, Status
from mvpose_core.transforms import Array


@dataclass
class _Camera:
    """One camera's learning buffer, baseline, CUSUM and cumulative residual sums."""

    warm: list[tuple[float, float]] = field(default_factory=list)
    mean: Array | None = None  # μ [2], px
    sigma: Array | None = None  # σ [2], px
    # The four one-sided statistics as :class:`Cusum` orders them, None while learning. Plain
    # floats: per trigger and camera, numpy's call overhead would cost ~10x the arithmetic.
    S: list[float] | None = None
    count: int = 0  # triggers since the baseline was set
    # station trigger index of each update since the baseline, and Σ (x − μ, in-fit fraction)
    # [3] after it; the oldest are dropped past ``DriftOptions.history`` (``floor`` keeps the
    # last dropped one)
    idx: list[int] = field(default_factory=list)
    cum: list[tuple[float, float, float]] = field(default_factory=list)
    floor: tuple[int, tuple[float, float, float]] = (-1, (0.0, 0.0, 0.0))
    starts: list[int] = field(default_factory=lambda: [0] * 4)  # where each run began
    mean_px: tuple[float, float] | None = None  # μ and σ as the state reports them
    sigma_px: tuple[float, float] | None = None


class ListDriftWatch:
    """The drift rule over every camera of a station, one trigger at a time.

    ``response[moved][seen]`` is the 2x2 matrix of :func:`mvpose_core.residuals.shift_response`
    (the mean residual of camera ``seen`` per px of image shift of camera ``moved``). With it
    the watch names the camera that moved and its move; without it, each camera is taken to
    have moved by what its own residuals show.
    """

    def __init__(
        self,
        options: DriftOptions = DriftOptions(),  # noqa: B008 - frozen, immutable default
        response: Response | None = None,
    ) -> None:
        self.options = options
        self._cams: dict[CameraKey, _Camera] = {}
        self._stamps: dict[int, float | None] = {}
        self._n = 0  # triggers seen
        self._response: dict[CameraKey, dict[CameraKey, Array]] = {}
        for moved, row in (response or {}).items():
            self._response[moved] = {}
            for seen, A in row.items():
                A = np.asarray(A, dtype=float)
                if A.shape != (2, 2) or not np.all(np.isfinite(A)):
                    raise ValueError(
                        f"response of camera {seen} to camera {moved}: expected a finite 2x2, "
                        f"got {A.tolist()}"
                    )
                self._response[moved][seen] = A

    @property
    def triggers(self) -> int:
        """Triggers seen so far (the next one gets this index)."""
        return self._n

    def set_baseline(self, key: CameraKey, mean_px: ArrayLike, sigma_px: ArrayLike) -> None:
        """Give a camera's in-control μ and σ (px, per component) instead of learning them."""
        mu = np.asarray(mean_px, dtype=float).reshape(2)
        sd = np.asarray(sigma_px, dtype=float).reshape(2)
        if not (np.all(np.isfinite(mu)) and np.all(np.isfinite(sd)) and np.all(sd > 0)):
            raise ValueError(
                f"camera {key}: a baseline needs finite μ and σ > 0, got {mu.tolist()}, "
                f"{sd.tolist()}"
            )
        self._start(self._cams.setdefault(key, _Camera()), mu, sd)

    def _start(self, cam: _Camera, mu: Array, sd: Array) -> None:
        cam.mean = mu
        cam.sigma = np.maximum(sd, self.options.min_sigma_px)
        cam.mean_px = (float(cam.mean[0]), float(cam.mean[1]))
        cam.sigma_px = (float(cam.sigma[0]), float(cam.sigma[1]))
        cam.S = [0.0] * 4
        cam.count, cam.idx, cam.cum = 0, [], []
        cam.floor = (self._n - 1, (0.0, 0.0, 0.0))
        cam.starts = [self._n] * 4
        cam.warm = []

    def update(
        self,
        means_px: Mapping[CameraKey, Array | tuple[float, float]],
        stamp: float | None = None,
        in_fit: Mapping[CameraKey, float] | None = None,
    ) -> None:
        """Feed one trigger: each camera's mean residual ``(du, dv)`` px (then ask
        :meth:`states` or :meth:`statistics`).

        A camera missing from ``means_px`` (no residual of it) skips this trigger. ``in_fit``
        is the fraction of each camera's observations the pose used (1 if not given; the robust
        rule leaves out a camera that moved far, which then shows its whole move).
        """
        n = self._n
        for key, value in means_px.items():
            u, v = (float(a) for a in value)
            f = 1.0 if in_fit is None else float(in_fit.get(key, 1.0))
            if not (math.isfinite(u) and math.isfinite(v) and 0.0 <= f <= 1.0):
                raise ValueError(
                    f"camera {key}: need a finite mean residual and an in-fit fraction in "
                    f"[0, 1], got {[u, v]}, {f}"
                )
            self._feed(self._cams.setdefault(key, _Camera()), n, u, v, f)
        self._stamps[n] = stamp
        self._n += 1
        if len(self._stamps) > 2 * self.options.history:
            keep = n - self.options.history
            self._stamps = {i: t for i, t in self._stamps.items() if i >= keep}

    def statistics(self) -> dict[CameraKey, float]:
        """Each camera's largest one-sided statistic, σ (0 while learning): cheap, per trigger."""
        return {k: (max(c.S) if c.S is not None else 0.0) for k, c in self._cams.items()}

    def _feed(self, cam: _Camera, n: int, u: float, v: float, in_fit: float) -> None:
        if cam.S is None:
            cam.warm.append((u, v))
            if len(cam.warm) >= self.options.warmup:
                w = np.asarray(cam.warm)
                self._start(cam, w.mean(axis=0), w.std(axis=0, ddof=1))
                cam.floor = (n, (0.0, 0.0, 0.0))
                cam.starts = [n + 1] * 4
            return
        assert cam.mean_px is not None and cam.sigma_px is not None
        du, dv = u - cam.mean_px[0], v - cam.mean_px[1]
        zu, zv = du / cam.sigma_px[0], dv / cam.sigma_px[1]
        k, S = self.options.k, cam.S
        for i, z in enumerate((zu, -zu, zv, -zv)):  # as Cusum.step, on floats
            new = max(0.0, S[i] + z - k)
            if S[i] == 0.0 and new > 0.0:
                cam.starts[i] = n  # a run starts here: the change point if it alarms
            S[i] = new
        cam.count += 1
        cam.idx.append(n)
        a, b, c = cam.cum[-1] if cam.cum else cam.floor[1]
        cam.cum.append((a + du, b + dv, c + in_fit))
        if len(cam.idx) > 2 * self.options.history:
            cut = len(cam.idx) - self.options.history
            cam.floor = (cam.idx[cut - 1], cam.cum[cut - 1])
            del cam.idx[:cut], cam.cum[:cut]

    @staticmethod
    def _since(cam: _Camera, n0: int) -> Array | None:
        """Means of ``(x − μ, in-fit fraction)`` ``[3]`` over the camera's triggers from ``n0``."""
        if not cam.idx or cam.idx[-1] < n0:
            return None
        j = bisect_left(cam.idx, n0)
        before = np.asarray(cam.cum[j - 1] if j > 0 else cam.floor[1])
        return (np.asarray(cam.cum[-1]) - before) / (len(cam.idx) - j)

    def _explain(self, key: CameraKey, n0: int, own: Array) -> tuple[CameraKey, Array]:
        """The camera whose move best explains every camera's residual shift since ``n0``.

        Least squares over every camera's standardised residual shift, one hypothesis per
        camera; the pose absorbs a moved camera's shift only while it is in the fit, so its
        response is blended with "shows it all" by its in-fit fraction.
        """
        if not self._response:
            return key, own
        seen: dict[CameraKey, tuple[Array, Array, float]] = {}  # shift/σ, σ, in-fit fraction
        for k, cam in self._cams.items():
            if cam.sigma is not None and (m := self._since(cam, n0)) is not None:
                seen[k] = (m[:2] / cam.sigma, cam.sigma, float(m[2]))
        best: tuple[float, CameraKey, Array] | None = None
        for moved, row in self._response.items():
            keys = [k for k in seen if k in row]
            if moved not in keys:
                continue
            f = seen[moved][2]
            blocks = [
                (f * row[k] + (1.0 - f) * np.eye(2) if k == moved else f * row[k])
                / seen[k][1][:, None]
                for k in keys
            ]
            B = np.vstack(blocks)
            r = np.concatenate([seen[k][0] for k in keys])
            s, *_ = np.linalg.lstsq(B, r, rcond=0.02)
            cost = float(np.sum((B @ s - r) ** 2))
            if best is None or cost < best[0]:
                best = (cost, moved, s)
        if best is None:
            return key, own
        return best[1], best[2]

    def state(self, key: CameraKey) -> CameraDrift:
        """Camera ``key``'s state (``KeyError`` if it was never seen)."""
        cam = self._cams[key]
        view, cid = key
        if cam.S is None or cam.mean is None or cam.sigma is None:
            n = len(cam.warm)
            return CameraDrift(
                view, cid, "learning", 0.0, None, None, None, None, None, n, None, None
            )
        S = cam.S
        peak = max(S)
        i = S.index(peak)
        o = self.options
        status: Status = "alarm" if peak >= o.h_alarm else "warning" if peak >= o.h_warn else "ok"
        moved = shift = residual = since = since_trigger = None
        if status != "ok":
            since_trigger = cam.starts[i]
            m = self._since(cam, since_trigger)
            if m is not None:
                r = m[:2]
                residual = (float(r[0]), float(r[1]))
                moved, s = self._explain(key, since_trigger, r)
                shift = (float(s[0]), float(s[1]))
            since = self._stamps.get(since_trigger)
        return CameraDrift(
            view=view,
            camera_id=cid,
            status=status,
            statistic=peak,
            moved=moved,
            shift_px=shift,
            residual_shift_px=residual,
            since=since,
            since_trigger=since_trigger,
            triggers=cam.count,
            mean_px=cam.mean_px,
            sigma_px=cam.sigma_px,
        )

    def states(self) -> list[CameraDrift]:
        """Every camera seen so far, by view then camera."""
        return [self.state(k) for k in sorted(self._cams)]
