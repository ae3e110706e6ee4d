"""Drift watch: a CUSUM per camera on the mean reprojection residual, to catch a camera that moved.

Rule. Each trigger gives per (view, camera) the mean residual vector ``x = (du, dv)`` px
(:func:`mvpose_core.residuals.camera_residuals`). In control, ``x`` scatters about a constant
``μ`` (the calibration's own small bias) with a standard deviation ``σ`` per component, both
learned from the first ``warmup`` triggers of the camera (or given). Each component is
standardised, ``z = (x − μ) / σ``, and watched by a two-sided CUSUM (Page 1954)::

    S⁺ ← max(0, S⁺ + z − k),    S⁻ ← max(0, S⁻ − z − k)

four one-sided statistics per camera (u up, u down, v up, v down). The camera is in *alarm* when
one of them reaches ``h_alarm`` and in *warning* when one reaches ``h_warn``. ``k = 0.5`` suits a
shift of one σ or more; ``h`` sets the false-alarm rate: the in-control average run length of
one one-sided statistic follows Siegmund's approximation (:func:`siegmund_arl`,
``ARL₀ ≈ 2(eᵇ − b − 1)`` with ``b = h + 1.166`` for k = 0.5), and a station of ``C`` cameras has
``4C`` of them, so its run length to a false alarm is about ``ARL₀ / 4C`` — shorter in
practice, as μ and σ are learned: with the defaults, a four-camera station has a 1.3 % chance of
a false alarm within 10,000 triggers. ``python -m bench drift`` measures this by simulation, and
the detection delays with the real estimator (docs/calibration.md, "Drift watch").

When a statistic alarms, the drift started where its current run began (the trigger at which
it last left zero, the CUSUM's change-point estimate). The pose estimate hides part of a
camera's move (it moves the part to fit the moved camera) and pushes part of it into the other
cameras' residuals: with the matrices of :func:`mvpose_core.residuals.shift_response`, the
watch fits every camera's mean residual shift since then with "camera c moved by s", for each
camera c, and reports the best fit: the camera that moved and its own image move, in px.

Pure numpy; no I/O, no clock: the caller passes each trigger's time stamp.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from mvpose_core.drift_history import History, Stamps
from mvpose_core.transforms import Array

#: Siegmund's correction of the CUSUM threshold for normal observations (ρ = −ζ(½)/√(2π))
SIEGMUND_B = 1.166

Status = Literal["learning", "ok", "warning", "alarm"]
CameraKey = tuple[int, str]  # (view, camera_id)


def siegmund_arl(shift_sigma: float, k: float, h: float) -> float:
    """Average run length of a one-sided CUSUM on N(δ, 1) data (δ = ``shift_sigma``).

    Siegmund's approximation ``(e^{−2Δb} + 2Δb − 1) / (2Δ²)`` with ``Δ = δ − k`` and
    ``b = h + 1.166`` (``b²`` when Δ = 0); within a few % of the exact value for h ≥ 3.
    """
    if not (k >= 0 and h > 0):
        raise ValueError(f"need k ≥ 0 and h > 0, got k={k}, h={h}")
    d = shift_sigma - k
    b = h + SIEGMUND_B
    if abs(d) < 1e-9:
        return b * b
    return float((np.exp(-2 * d * b) + 2 * d * b - 1) / (2 * d * d))


def threshold_for_arl(arl0: float, k: float = 0.5) -> float:
    """The ``h`` whose in-control run length (:func:`siegmund_arl` at δ = 0) is ``arl0``."""
    if not arl0 > 1:
        raise ValueError(f"arl0 must be > 1 trigger, got {arl0}")
    lo, hi = 0.01, 100.0
    for _ in range(100):  # bisection: the ARL grows monotonically with h
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if siegmund_arl(0.0, k, mid) < arl0 else (lo, mid)
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class DriftOptions:
    """The rule's constants (defaults: docs/calibration.md, "Drift watch")."""

    k: float = 0.5  # reference value, σ: half the smallest shift to catch quickly
    h_warn: float = 12.0  # σ; one one-sided statistic's ARL₀ ≈ 1.0e6 triggers (known μ, σ)
    h_alarm: float = 16.0  # σ; one one-sided statistic's ARL₀ ≈ 5.7e7 triggers (known μ, σ)
    # triggers per camera to learn μ and σ: their errors shorten the run length to a false
    # alarm (μ off by 0.045 σ after 500 triggers): bench/bench_drift.py simulates it in
    warmup: int = 500
    min_sigma_px: float = 0.002  # σ floor: a noise-free camera must not make z infinite
    history: int = 20_000  # triggers kept to date a drift and estimate its shift

    def __post_init__(self) -> None:
        if not self.k >= 0:
            raise ValueError(f"k must be ≥ 0, got {self.k}")
        if not 0 < self.h_warn <= self.h_alarm:
            raise ValueError(
                f"need 0 < h_warn ≤ h_alarm, got h_warn={self.h_warn}, h_alarm={self.h_alarm}"
            )
        if self.warmup < 2:
            raise ValueError(f"warmup must be ≥ 2 triggers, got {self.warmup}")
        if not self.min_sigma_px > 0:
            raise ValueError(f"min_sigma_px must be > 0, got {self.min_sigma_px}")
        if self.history < 1:
            raise ValueError(f"history must be ≥ 1 trigger, got {self.history}")


class Cusum:
    """Two-sided CUSUMs on standardised data, vectorised over any leading shape.

    ``step(z)`` takes ``z`` of shape ``[..., 2]`` (u, v) and keeps ``S`` of shape ``[..., 4]``:
    (u up, u down, v up, v down). :class:`DriftWatch` runs one per camera; the simulations in
    bench/bench_drift.py run thousands in parallel with the same code.
    """

    def __init__(self, shape: tuple[int, ...], k: float) -> None:
        self.k = k
        self.S = np.zeros((*shape, 4))

    def step(self, z: Array) -> None:
        """Advance one trigger with ``z`` ``[..., 2]`` (standardised u, v)."""
        z = np.asarray(z, dtype=float)
        signed = np.concatenate([z[..., :1], -z[..., :1], z[..., 1:2], -z[..., 1:2]], axis=-1)
        self.S = np.maximum(0.0, self.S + signed - self.k)

    @property
    def peak(self) -> Array:
        """The largest of the four statistics ``[...]``."""
        return self.S.max(axis=-1)


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
    # the updates since the baseline, the last ``DriftOptions.history`` kept (None while learning)
    history: History | None = None
    starts: list[int] = field(default_factory=lambda: [0] * 4)  # where each run began
    mean_px: tuple[float, float] | None = None  # μ and σ as the state reports them
    sigma_px: tuple[float, float] | None = None


@dataclass(frozen=True)
class CameraDrift:
    """A camera's state after the last trigger.

    ``moved`` is the camera whose move explains the residual shifts of every camera best since
    this camera's statistic started to rise (with a full :func:`shift_response`; a moved camera
    pushes a part of its shift into the other cameras' residuals through the pose, so the
    camera that alarms first is not always the one that moved). ``shift_px`` is that camera's
    estimated image move, px.
    """

    view: int
    camera_id: str
    status: Status
    statistic: float  # the largest one-sided CUSUM, σ (0 while learning)
    moved: CameraKey | None  # (view, camera) that moved, when status is warning or alarm
    shift_px: tuple[float, float] | None  # its image move since ``since``, px
    residual_shift_px: tuple[float, float] | None  # this camera's residual shift since, px
    since: float | None  # time stamp of the trigger the drift started at (the caller's clock)
    since_trigger: int | None  # that trigger's index (0 = the first trigger the watch saw)
    triggers: int  # triggers of this camera since its baseline (while learning: learnt from)
    mean_px: tuple[float, float] | None  # baseline μ
    sigma_px: tuple[float, float] | None  # baseline σ

    @property
    def key(self) -> CameraKey:
        return (self.view, self.camera_id)

    @property
    def shift_norm_px(self) -> float | None:
        return None if self.shift_px is None else float(np.hypot(*self.shift_px))


Response = Mapping[CameraKey, Mapping[CameraKey, Array]]


class DriftWatch:
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
        self._stamps = Stamps(options.history)
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
        cam.count = 0
        cam.history = History(self.options.history, self._n - 1)
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
        self._stamps.append(stamp)
        self._n += 1

    def statistics(self) -> dict[CameraKey, float]:
        """Each camera's largest one-sided statistic, σ (0 while learning): cheap, per trigger."""
        return {k: (max(c.S) if c.S is not None else 0.0) for k, c in self._cams.items()}

    def _feed(self, cam: _Camera, n: int, u: float, v: float, in_fit: float) -> None:
        if cam.S is None:
            cam.warm.append((u, v))
            if len(cam.warm) >= self.options.warmup:
                w = np.asarray(cam.warm)
                self._start(cam, w.mean(axis=0), w.std(axis=0, ddof=1))
                assert cam.history is not None
                cam.history.floor_at = n
                cam.starts = [n + 1] * 4
            return
        assert cam.mean_px is not None and cam.sigma_px is not None and cam.history is not None
        du, dv = u - cam.mean_px[0], v - cam.mean_px[1]
        zu, zv = du / cam.sigma_px[0], dv / cam.sigma_px[1]
        k, S = self.options.k, cam.S
        for i, z in enumerate((zu, -zu, zv, -zv)):  # as Cusum.step, on floats
            new = max(0.0, S[i] + z - k)
            if S[i] == 0.0 and new > 0.0:
                cam.starts[i] = n  # a run starts here: the change point if it alarms
            S[i] = new
        cam.count += 1
        cam.history.append(n, du, dv, in_fit)

    @staticmethod
    def _since(cam: _Camera, n0: int) -> Array | None:
        """Means of ``(x − μ, in-fit fraction)`` ``[3]`` over the camera's triggers from ``n0``."""
        return None if cam.history is None else cam.history.since(n0)

    @property
    def history_nbytes(self) -> int:
        """Bytes the history holds now (its arrays, allocated at the full ``history``)."""
        cams = sum(c.history.nbytes for c in self._cams.values() if c.history is not None)
        return cams + int(self._stamps.t.nbytes)

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


def camera_name(key: CameraKey) -> str:
    """``camera cam2``, with the view when it is not the first."""
    return f"camera {key[1]}" + (f" (view {key[0]})" if key[0] != 1 else "")


def drift_message(d: CameraDrift, since_text: str | None = None) -> str:
    """One line for an operator: "camera cam2 moved ~0.4 px since 08:12" (or its calm state)."""
    if d.status == "learning":
        return f"{camera_name(d.key)}: learning its noise level"
    if d.status == "ok" or d.shift_norm_px is None or d.moved is None:
        return f"{camera_name(d.key)}: no drift"
    name = camera_name(d.moved)
    when = f" since {since_text}" if since_text else ""
    verb = "moved" if d.status == "alarm" else "may have moved"
    size = d.shift_norm_px
    return f"{name} {verb} ~{size:.{1 if size >= 0.1 else 2}f} px{when}"
