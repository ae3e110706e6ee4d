"""Timing helpers shared by the benchmarks: repeated runs, median and p99, target checks."""

from __future__ import annotations

import gc
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Timing:
    name: str
    samples_ms: np.ndarray

    @property
    def median(self) -> float:
        return float(np.median(self.samples_ms))

    @property
    def p99(self) -> float:
        return float(np.percentile(self.samples_ms, 99))

    def line(self, ref: Timing | None = None) -> str:
        s = (
            f"{self.name:<52} median {self.median:9.3f} ms   p99 {self.p99:9.3f} ms"
            f"   n={len(self.samples_ms)}"
        )
        if ref is not None and ref.median > 0:
            s += f"   ratio {self.median / ref.median:6.2f}x vs {ref.name}"
        return s


def measure(name: str, fn: Callable[[], object], repeat: int = 200, warmup: int = 10) -> Timing:
    """Call ``fn`` ``repeat`` times (after ``warmup`` calls) and keep every duration in ms."""
    for _ in range(warmup):
        fn()
    samples = np.empty(repeat)
    gc_was = gc.isenabled()
    gc.disable()
    try:
        for i in range(repeat):
            t0 = time.perf_counter()
            fn()
            samples[i] = (time.perf_counter() - t0) * 1e3
    finally:
        if gc_was:
            gc.enable()
    return Timing(name, samples)


def check(label: str, value: float, target: float) -> bool:
    """Print whether ``value`` (ms) meets ``target`` and return True when it does."""
    ok = value <= target
    print(f"  target {label}: {value:.3f} ms <= {target:.3f} ms ... {'OK' if ok else 'MISSED'}")
    return ok
