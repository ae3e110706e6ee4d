"""Calibration accuracy against known truth (issue 5 targets) and the time of a hand-eye solve."""

from __future__ import annotations

import numpy as np

from bench.timing import measure
from mvpose_core.calibration.handeye import build_problem, calibrate_handeye
from mvpose_core.calibration.intrinsics import calibrate_intrinsics
from mvpose_core.calibration.stereo import calibrate_stereo
from mvpose_core.calibration.synthetic import make_scene
from mvpose_core.transforms import transform_error

SEEDS = range(10)
NOISE_PX = 0.1


def _chain(seed: int) -> dict[str, float]:
    """Intrinsics → stereo → hand-eye on 15 robot poses, stereo rig, 0.1 px noise."""
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, n_poses=15)
    det = scene.observe(rng, NOISE_PX)
    true = scene.cameras["left"]
    size = (true.width, true.height)
    left = calibrate_intrinsics("left", det["left"], scene.board, size)
    right = calibrate_intrinsics("right", det["right"], scene.board, size)
    st = calibrate_stereo(
        "left", "right", det["left"], det["right"], scene.board, left.camera, right.camera
    )
    problem, _ = build_problem(
        "robot",
        scene.board,
        {"left": st.model1, "right": st.model2},
        scene.robot_poses,
        det,
        {"right": st.T_cf2_from_cf1},
    )
    he = calibrate_handeye(problem)
    deg, mm = transform_error(he.X, scene.X)
    baseline = float(np.linalg.norm(scene.T_cfc_from_cf0["right"][:3, 3]))
    return {
        "focal %": 100 * abs(he.cameras["left"].fx / true.fx - 1),
        "baseline mm": abs(float(np.linalg.norm(he.T_cfc_from_cf0["right"][:3, 3])) - baseline),
        "hand-eye mm": mm,
        "hand-eye deg": deg,
        "1σ mm": he.sigma_mm,
        "1σ deg": he.sigma_deg,
    }


def main() -> int:
    rows = [_chain(s) for s in SEEDS]
    targets = {"focal %": 0.1, "baseline mm": 0.1, "hand-eye mm": 0.2, "hand-eye deg": 0.02}
    ok = True
    print(f"{len(rows)} scenes, 15 robot poses, stereo rig, {NOISE_PX} px noise")
    for key in rows[0]:
        v = np.array([r[key] for r in rows])
        line = f"  {key:<14} rms {np.sqrt(np.mean(v**2)):.4f}   max {v.max():.4f}"
        if key in targets:
            met = int(np.sum(v <= targets[key]))
            line += f"   target {targets[key]}: {met}/{len(v)} scenes"
            ok &= bool(np.sqrt(np.mean(v**2)) <= targets[key])
        print(line)
    for a, b in (("hand-eye mm", "1σ mm"), ("hand-eye deg", "1σ deg")):
        err = np.sqrt(np.mean([r[a] ** 2 for r in rows]))
        sig = np.mean([r[b] for r in rows])
        ratio = err / sig
        print(f"  spread/1σ {a:<13} {ratio:.2f} (target within 1/1.5 … 1.5)")
        ok &= bool(1 / 1.5 <= ratio <= 1.5)
    rng = np.random.default_rng(0)
    scene = make_scene(rng, n_poses=15)
    det = scene.observe(rng, NOISE_PX)
    problem, _ = build_problem(
        "robot", scene.board, scene.cameras, scene.robot_poses, det, scene.T_cfc_from_cf0
    )
    print(
        measure(
            "calibrate_handeye, 15 poses, stereo, joint refine",
            lambda: calibrate_handeye(problem),
            repeat=5,
            warmup=1,
        ).line()
    )
    return 0 if ok else 1
