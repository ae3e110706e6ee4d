"""Drift watch figures (docs/calibration.md, "Drift watch"): false-alarm rate and detection delays.

Part 1, the rule alone on N(0, 1) data: Siegmund's run lengths against simulation, and a
station's chance of a false alarm within 10,000 triggers with μ and σ learned from the warm-up.
Part 2, each station in deploy/stations with the real estimator (mvpose_core.measure on
synthetic observations, parts placed at random within ±5 mm / ±0.5°): every camera moved by
0.2, 0.5 and 1 px along u and along v after the warm-up; triggers until the alarm, the camera
named and the move estimated; then 10,000 in-control triggers drawn from real measurements.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import numpy as np

from mvpose_core.drift import Cusum, DriftOptions, DriftWatch, siegmund_arl
from mvpose_core.residuals import TriggerResiduals, shift_response, simulated_residuals
from mvpose_core.station import load_station

Array = np.ndarray
STATIONS = Path(__file__).resolve().parents[1] / "deploy" / "stations"
SHIFTS_PX = (0.2, 0.5, 1.0)
RUNS = 4  # drift runs per camera, direction and shift
POOL = 1000  # in-control triggers the 10,000-trigger runs are drawn from
IN_CONTROL = 10_000
#: the delays docs/calibration.md states: triggers from the move to the alarm, at most
STATED_DELAY = {0.2: 200, 0.5: 30, 1.0: 12}
#: and the false-alarm chance within 10,000 triggers of a four-camera station, at most
STATED_FALSE_ALARM = 0.02
#: the same drawn from POOL real measurements: pessimistic, as the pool's own sampling error
#: (0.03 σ) adds to the warm-up's
STATED_FALSE_ALARM_POOL = 0.05


def run_lengths(rng: np.random.Generator, shift: float, k: float, h: float, runs: int) -> Array:
    """Run lengths of one one-sided CUSUM (known μ, σ) on N(shift, 1), ``runs`` in parallel."""
    c = Cusum((runs,), k)
    length = np.zeros(runs, dtype=int)
    n = 0
    while (length == 0).any():
        n += 1
        c.step(np.stack([rng.normal(shift, 1.0, runs), np.zeros(runs)], axis=-1))
        length[(length == 0) & (c.S[:, 0] >= h)] = n
    return length


def false_alarm_chance(
    rng: np.random.Generator, o: DriftOptions, cameras: int, runs: int, triggers: int
) -> tuple[float, float]:
    """P(warning) and P(alarm) within ``triggers`` for a station, μ and σ learned per run."""
    w = rng.standard_normal((o.warmup, runs, cameras, 2))
    mu, sd = w.mean(axis=0), w.std(axis=0, ddof=1)
    c = Cusum((runs, cameras), o.k)
    peak = np.zeros(runs)
    for _ in range(triggers):
        c.step((rng.standard_normal((runs, cameras, 2)) - mu) / sd)
        peak = np.maximum(peak, c.peak.max(axis=-1))
    return float(np.mean(peak >= o.h_warn)), float(np.mean(peak >= o.h_alarm))


def part1(rng: np.random.Generator, o: DriftOptions) -> bool:
    print(f"rule: k = {o.k}, h_warn = {o.h_warn}, h_alarm = {o.h_alarm}, warm-up {o.warmup}")
    print("  one one-sided CUSUM, known μ and σ: run length, Siegmund vs simulated (mean of 2000)")
    for shift, h in ((0.0, 4.0), (0.0, 6.0), (0.5, o.h_alarm), (1.0, o.h_alarm), (2.0, o.h_alarm)):
        sim = run_lengths(rng, shift, o.k, h, 2000).mean()
        print(
            f"    shift {shift:.1f} σ, h = {h:4.1f}: Siegmund {siegmund_arl(shift, o.k, h):8.1f}"
            f"   simulated {sim:8.1f}"
        )
    arl_warn, arl_alarm = (siegmund_arl(0.0, o.k, h) for h in (o.h_warn, o.h_alarm))
    print(
        f"  in-control ARL of one statistic (Siegmund): warning {arl_warn:.3g}, "
        f"alarm {arl_alarm:.3g} triggers; a station of C cameras has 4C of them"
    )
    p_warn, p_alarm = false_alarm_chance(rng, o, 4, 2000, IN_CONTROL)
    arl = -IN_CONTROL / np.log1p(-p_alarm) if p_alarm > 0 else float("inf")
    print(
        f"  4 cameras, μ and σ learned from {o.warmup} triggers, 2000 runs of "
        f"{IN_CONTROL} triggers: P(warning) {p_warn:.3f}, P(alarm) {p_alarm:.4f} "
        f"(run length to a false alarm ≈ {arl:.3g} triggers)"
    )
    return p_alarm <= STATED_FALSE_ALARM


def _learn(watch: DriftWatch, triggers: list[TriggerResiduals]) -> None:
    for i, t in enumerate(triggers):
        watch.update(t.means_px, float(i), t.in_fit)


def part2(name: str, rng: np.random.Generator, o: DriftOptions) -> tuple[bool, dict[float, int]]:
    station = load_station(STATIONS / f"{name}.yaml")
    recipe = station.recipes[0]
    response = shift_response(station, recipe)
    keys = sorted(response)
    watch = DriftWatch(o, response)
    t0 = time.perf_counter()
    _learn(watch, simulated_residuals(station, recipe, rng, o.warmup))
    ms = (time.perf_counter() - t0) / o.warmup * 1e3
    print(
        f"\n{name}: {len(keys)} cameras, {o.warmup} warm-up triggers ({ms:.1f} ms each, real "
        f"estimator); σ of the mean residual, px:"
    )
    for st in watch.states():
        assert st.sigma_px is not None
        own = np.diag(response[st.key][st.key])
        print(
            f"  {st.camera_id:<12} view {st.view}  σ ({st.sigma_px[0]:.4f}, {st.sigma_px[1]:.4f})"
            f"  residual keeps ({own[0]:.2f}, {own[1]:.2f}) of a move"
        )
    ok = True
    worst: dict[float, int] = {}
    for shift in SHIFTS_PX:
        delays, right, errors, dating = [], 0, [], []
        for key in keys:
            for axis in (0, 1):
                move = (shift, 0.0) if axis == 0 else (0.0, shift)
                for _ in range(RUNS):
                    w = copy.deepcopy(watch)
                    start = w.triggers
                    n = 0
                    alarm = None
                    while alarm is None and n < 1000:
                        t = simulated_residuals(station, recipe, rng, 1, shift_px={key: move})[0]
                        n += 1
                        w.update(t.means_px, None, t.in_fit)
                        hits = [d for d in w.states() if d.status == "alarm"]
                        alarm = hits[0] if hits else None
                    delays.append(n)
                    if alarm is not None and alarm.moved == key:
                        right += 1
                    if alarm is not None and alarm.shift_norm_px is not None:
                        errors.append(alarm.shift_norm_px - shift)
                    if alarm is not None and alarm.since_trigger is not None:
                        dating.append(alarm.since_trigger - start)
        d = np.array(delays)
        worst[shift] = int(d.max())
        ok &= worst[shift] <= STATED_DELAY[shift]
        e, a = np.array(errors), np.abs(np.array(dating))
        print(
            f"  moved {shift:.1f} px ({len(d)} runs: {len(keys)} cameras x u, v x {RUNS}): "
            f"alarm after median {np.median(d):.0f}, p90 {np.percentile(d, 90):.0f}, "
            f"max {d.max()} triggers (stated ≤ {STATED_DELAY[shift]}); camera named right "
            f"{right}/{len(d)}; move estimate error median {np.median(np.abs(e)):.2f} px; "
            f"start dated {np.median(a):.0f} (max {a.max()}) triggers off"
        )
    pool = simulated_residuals(station, recipe, rng, POOL)
    means = np.array([[t.means_px[k] for k in keys] for t in pool])  # [POOL, C, 2]
    states = {d.key: d for d in watch.states()}
    mu = np.array([states[k].mean_px for k in keys])
    sd = np.array([states[k].sigma_px for k in keys])
    runs = 100
    c = Cusum((runs, len(keys)), o.k)
    peak = np.zeros(runs)
    for _ in range(IN_CONTROL):
        x = means[rng.integers(0, POOL, runs)]
        c.step((x - mu) / sd)
        peak = np.maximum(peak, c.peak.max(axis=-1))
    alarms = int(np.sum(peak >= o.h_alarm))
    print(
        f"  no drift: {runs} runs of {IN_CONTROL} triggers drawn from {POOL} real "
        f"measurements: {alarms} with an alarm, {int(np.sum(peak >= o.h_warn))} with a warning"
    )
    return ok and alarms <= runs * STATED_FALSE_ALARM_POOL, worst


def main() -> int:
    rng = np.random.default_rng(17)
    o = DriftOptions()
    ok = part1(rng, o)
    for name in ("station1", "station2", "lab"):
        good, _ = part2(name, rng, o)
        ok &= good
    print(
        f"\nstated delays {STATED_DELAY} triggers and false-alarm chance "
        f"≤ {STATED_FALSE_ALARM} met: {ok}"
    )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
