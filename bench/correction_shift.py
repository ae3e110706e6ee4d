"""How far the perspective correction moves when the part is off its taught pose (detection.md).

Detection applies the correction computed at the recipe's prior (taught) pose; the server then
recomputes it at the estimated pose and measures again only if some mark's correction moved by
more than ``PipelineOptions.recorrect_px``. This prints, per example station and displacement
size (uniform per axis, ``mvpose_core.synth.random_displacement``), the size of the correction at
the taught pose and how far it moves: median and maximum over every sighted mark of every camera.
Run: ``python -m bench.correction_shift [trials]`` (default 40 displaced poses per row).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mvpose_core.detect import perspective_corrections
from mvpose_core.scene import sighted_marks, view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import random_displacement

STATIONS = Path(__file__).resolve().parents[1] / "deploy" / "stations"
DISPLACEMENTS = ((1.0, 0.1), (5.0, 0.5), (20.0, 2.0), (50.0, 5.0), (100.0, 10.0))


def main(trials: int = 40) -> int:
    rng = np.random.default_rng(11)
    for name in ("lab", "station1", "station2"):
        station = load_station(STATIONS / f"{name}.yaml")
        recipe = station.recipe()
        items = [(vc, sighted_marks(recipe, vc.view, vc.camera_id)) for vc in view_cameras(station)]
        T0 = recipe.T_rf_from_pf0.matrix
        at_prior = perspective_corrections(items, recipe, T0)
        size = [float(np.linalg.norm(c)) for cam in at_prior for c in cam.values()]
        tol = recipe.tolerances
        print(f"{name}: |correction| at the taught pose {min(size):.3f}-{max(size):.3f} px; "
              f"recipe tolerance ±{tol.max_offset_mm:g} mm / ±{tol.max_offset_deg:g}°")
        for mm, deg in DISPLACEMENTS:
            moved: list[float] = []
            for _ in range(trials):
                T = T0 @ random_displacement(rng, mm, deg)
                for before, after in zip(at_prior, perspective_corrections(items, recipe, T),
                                         strict=True):
                    moved += [float(np.linalg.norm(after[m] - c)) for m, c in before.items()
                              if m in after]
            print(f"  part within ±{mm:5.1f} mm / ±{deg:4.1f}°: correction moves by median "
                  f"{np.median(moved):.4f} px, max {np.max(moved):.4f} px")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(*(int(a) for a in sys.argv[1:2])))
