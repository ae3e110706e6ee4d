"""Issue 26, item 2: the reported 1σ against the actual error on three kinds of station, and the
steep camera's mark through the station path against the detector called alone.

Stations of tests/mvpose_core/real_stations.py: the bonnet (three fixed cameras, one tilted 35°,
five mark diameters; part frame 1.7 m away), the front floor (a robot-mounted stereo rig, two
views) and the compact panel (four fixed cameras; the steep one: 35°, 12 mm lens on 2048², k1
−0.11, a 14 mm mark of ~25 px radius at v ≈ 1620). Parts within ±5 mm / ±0.5° of the taught pose,
rendered with clutter. Per station: RMS error at the grasp frame against the RMS reported 1σ
(``Measurement.sigma_rot_deg`` / ``sigma_trans_mm``), with each centre's σ from its mark's size
and contrast (the model) and with one σ for every centre (``centre_variance`` dropped: the
model before it). Then, on the compact panel, the centre error RMS of the pipeline's path
(windows at the taught pose, the correction at the estimate when it moved by more than 0.01 px)
against ``detect_marks`` + ``correct_centres`` at the true pose on the same images.
Run: ``python -m bench.station_uncertainty [--trials N] [--seed S]``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "mvpose_core"))

from real_stations import bonnet, compact, floor  # noqa: E402

from mvpose_core.detect import (  # noqa: E402
    DetectOptions,
    correct_centres,
    detect_marks,
    detect_marks_many,
    recorrect,
)
from mvpose_core.measure import measure  # noqa: E402
from mvpose_core.render import RenderOptions, render_view  # noqa: E402
from mvpose_core.robust import observations_of  # noqa: E402
from mvpose_core.scene import view_cameras  # noqa: E402
from mvpose_core.simulation.rendered import displaced_about_marks  # noqa: E402
from mvpose_core.station import StationConfig  # noqa: E402
from mvpose_core.transforms import transform_error  # noqa: E402

OPTIONS = RenderOptions(supersample=8, clutter=True)


def _rms(x: object) -> float:
    return float(np.sqrt(np.mean(np.square(np.asarray(x, dtype=float)))))


def sigma_rows(st: StationConfig, trials: int, rng: np.random.Generator) -> list[str]:
    rec = st.recipe()
    cams = view_cameras(st)
    G = rec.T_pf_from_grasp.matrix
    runs: dict[str, list[tuple[float, float, float, float]]] = {"per mark": [], "one σ": []}
    for _ in range(trials):
        T = displaced_about_marks(rec, rng, 5.0, 0.5)
        obs = []
        for view in sorted({c.view for c in cams}):
            vcs = [c for c in cams if c.view == view]
            frames = [(render_view(vc, rec, T, rng, OPTIONS).image, vc) for vc in vcs]
            dets = detect_marks_many(frames, rec, rec.T_rf_from_pf0.matrix)
            obs += observations_of(view, {vc.camera_id: d for vc, d in zip(vcs, dets, strict=True)})
        for name, given in (("per mark", obs), ("one σ", [replace(o, centre_variance=None)
                                                           for o in obs])):
            m = measure(st, rec, given, cameras=cams)
            rot, trans = transform_error(m.T_rf_from_pf @ G, T @ G)
            runs[name].append((rot, trans, m.sigma_rot_deg, m.sigma_trans_mm))
    rows = []
    for name, v in runs.items():
        a = np.array(v)
        act, rep = (_rms(a[:, 0]), _rms(a[:, 1])), (_rms(a[:, 2]), _rms(a[:, 3]))
        rows.append(f"| {st.name} | {name} | {act[0]:.5f}° / {act[1]:.4f} mm | "
                    f"{rep[0]:.5f}° / {rep[1]:.4f} mm | {act[0] / rep[0]:.2f} / "
                    f"{act[1] / rep[1]:.2f} |")
    return rows


def steep_path(trials: int, rng: np.random.Generator) -> str:
    st = compact()
    rec = st.recipe()
    cams = view_cameras(st)
    prior = rec.T_rf_from_pf0.matrix
    station: dict[str, list[np.ndarray]] = {"steep": [], "all": []}
    direct: dict[str, list[np.ndarray]] = {"steep": [], "all": []}
    for _ in range(trials):
        T = displaced_about_marks(rec, rng, 8.0, 0.8)
        rendered = [render_view(vc, rec, T, rng, OPTIONS) for vc in cams]
        frames = [(r.image, vc) for r, vc in zip(rendered, cams, strict=True)]
        found = detect_marks_many(frames, rec, prior, DetectOptions(correct_perspective=True))
        groups = [(vc, d) for (_, vc), d in zip(frames, found, strict=True)]
        m = measure(st, rec, [o for vc, d in groups for o in observations_of(
            1, {vc.camera_id: d})], cameras=cams)
        moved, shift = recorrect(groups, rec, m.T_rf_from_pf)
        final = moved if shift > 0.01 else [d for _, d in groups]
        for r, vc, dets in zip(rendered, cams, final, strict=True):
            alone = correct_centres(detect_marks(r.image, vc, rec, prior), vc, rec, T)
            for a, b in zip(dets, alone, strict=True):
                if not (a.found and b.found):
                    continue
                for key in ("all", "steep") if vc.camera_id == "steep" else ("all",):
                    station[key].append(a.uv - r.centres[a.mark_id])
                    direct[key].append(b.uv - r.centres[b.mark_id])
    s, d = _rms(station["steep"]), _rms(direct["steep"])
    bias = np.mean(station["steep"], axis=0)
    return (f"compact_0 steep/M2, {trials} triggers: station path {s:.4f} px RMS (bias "
            f"{bias[0]:+.4f} / {bias[1]:+.4f} px), detector alone {d:.4f} px ({s / d:.2f}x); "
            f"every centre: {_rms(station['all']):.4f} against {_rms(direct['all']):.4f} px")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.station_uncertainty", description=__doc__)
    p.add_argument("--trials", type=int, default=60)
    p.add_argument("--seed", type=int, default=26)
    args = p.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    print("| station | centre σ | actual RMS (rot / grasp) | reported RMS | actual / reported |")
    print("|---|---|---|---|---|")
    for st in (bonnet(1700.0), floor(1700.0), compact(0.0)):
        for row in sigma_rows(st, args.trials, rng):
            print(row, flush=True)
    print(steep_path(max(args.trials // 3, 4), rng))
    return 0


if __name__ == "__main__":
    sys.exit(main())
