"""Issue 26, item 1: the stereo and fixed-station calibrations' reported 1σ against their actual
error over seeded Monte Carlo sets (tests/mvpose_core/calibration_sets.py: the lab rig at 0.1 px,
15 poses; three fixed cameras in a row, 12 placements), and the station's camera-to-camera error
against the images-only adjustment started from the true intrinsics and against each camera's
own intrinsics held (the station path before). Fails when a ratio leaves 0.7–1.4 or the station
is more than 1.5× the images-only adjustment.
Run: ``python -m bench.calibration_uncertainty [--sets N]``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "mvpose_core"))

from calibration_sets import Run, ratios, rms, station_runs, stereo_run  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sets", type=int, default=40, help="Monte Carlo sets per kind")
    args = ap.parse_args(argv if argv is not None else [])
    ok = True
    st = [stereo_run(1000 + k) for k in range(args.sets)]
    t, r = ratios(st)
    e = rms([x.error for x in st])
    print(
        f"stereo, {len(st)} sets: actual/reported translation {t:.2f}, rotation {r:.2f}; "
        f"RMS error {e[0]:.3f} mm / {e[1]:.4f}°"
    )
    ok &= 0.7 <= t <= 1.4 and 0.7 <= r <= 1.4
    runs: list[Run] = []
    seed = 2000
    while len(runs) < 2 * args.sets:
        got = station_runs(seed)
        seed += 1
        runs += got or []
    t, r = ratios(runs)
    ours = rms([x.error for x in runs])
    ref = rms([x.reference_error for x in runs])
    held = rms([x.held_error for x in runs])
    print(
        f"station, {len(runs)} camera pairs ({seed - 2000} sets tried): actual/reported "
        f"translation {t:.2f}, rotation {r:.2f}; camera-to-camera RMS error {ours[0]:.3f} mm / "
        f"{ours[1]:.4f}°, images-only adjustment {ref[0]:.3f} mm / {ref[1]:.4f}°, own "
        f"intrinsics held {held[0]:.3f} mm / {held[1]:.4f}°"
    )
    ok &= 0.7 <= t <= 1.4 and 0.7 <= r <= 1.4
    ok &= ours[0] <= 1.5 * ref[0] and ours[1] <= 1.5 * ref[1]
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
