"""One pose estimate (start + refine + covariance), 4 cameras, 4/8/16 marks, against PoseLib.

Scene: the lab station (deploy/stations/lab.yaml): a stereo pair at two views = 4 cameras,
half of the marks in each view's field, seen by both cameras of that view, σ = 0.5 px.
PoseLib's ``estimate_generalized_absolute_pose`` (RANSAC + refinement, OPENCV camera model)
gets identical data: world = part frame, rig = robot base, camera_ext = T_cf_from_rf.
A second scene, station 1 (4 fixed cameras, no overlap, 8 marks), times the generalised-DLT start.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from bench.timing import check, measure
from mvpose_core.estimate import Observation, estimate_pose
from mvpose_core.scene import ViewCamera, view_cameras
from mvpose_core.station import load_station
from mvpose_core.synth import synthetic_observations
from mvpose_core.transforms import invert, transform_error

ROOT = Path(__file__).resolve().parents[1]
TARGET_MEDIAN_MS = 0.5
TARGET_P99_MS = 1.0
POSELIB_RATIO = 2.0  # issue 28: ours within 2x PoseLib's, measured in the same process
SIGMA_PX = 0.5
#: calls before timing, for both libraries: the first case otherwise pays for a cold process
#: (its median came out 1.3-1.9x the 8-mark case's though it does the same work)
WARMUP = 300


def lab_scene(
    n_marks: int, rng: np.random.Generator
) -> tuple[list[ViewCamera], dict[str, np.ndarray], list[Observation], np.ndarray]:
    """Cameras, marks (PF), noisy observations and the true pose for the lab with n marks."""
    st = load_station(ROOT / "deploy" / "stations" / "lab.yaml")
    cams = view_cameras(st)
    T_true = st.recipe().T_rf_from_pf0.matrix
    marks: dict[str, np.ndarray] = {}
    obs: list[Observation] = []
    for i in range(n_marks):
        view = 1 + i % 2  # view 1 looks at x ≈ −550 mm, view 2 at x ≈ +550 mm
        p = np.array(
            [
                (-550.0 if view == 1 else 550.0) + rng.uniform(-200, 200),
                rng.uniform(-250, 250),
                rng.uniform(-30, 30),
            ]
        )
        marks[f"M{i + 1}"] = p
        for cam in cams:
            if cam.view != view:
                continue
            T_cf_from_pf = invert(cam.T_rf_from_cf) @ T_true
            uv = cam.model.project((T_cf_from_pf[:3, :3] @ p + T_cf_from_pf[:3, 3])[None])[0]
            obs.append(
                Observation(view, cam.camera_id, f"M{i + 1}", uv + rng.normal(0, SIGMA_PX, 2))
            )
    return cams, marks, obs, T_true


def poselib_call(
    cams: list[ViewCamera], marks: dict[str, np.ndarray], obs: list[Observation]
) -> Callable[[], Any]:
    """A closure running PoseLib's generalized absolute pose on the same observations."""
    import poselib

    p2d, p3d, ext, cam_dicts = [], [], [], []
    for cam in cams:
        mine = [o for o in obs if (o.view, o.camera_id) == (cam.view, cam.camera_id)]
        if not mine:
            continue
        p2d.append(np.array([o.uv for o in mine]))
        p3d.append(np.array([marks[o.mark_id] for o in mine]))
        T = invert(cam.T_rf_from_cf)
        pose = poselib.CameraPose()
        pose.R = T[:3, :3]
        pose.t = T[:3, 3]
        ext.append(pose)
        m = cam.model
        cam_dicts.append(
            {
                "model": "OPENCV",
                "width": m.width,
                "height": m.height,
                "params": [m.fx, m.fy, m.cx, m.cy, *m.dist[:4]],
            }
        )
    # PoseLib defaults except the threshold (4 px) and min_iterations (default 1000 trials even on
    # outlier-free data): 50 keeps RANSAC honest without paying for 1000 minimal solves.
    ransac = {"max_reproj_error": 4.0, "min_iterations": 50}

    def run() -> Any:
        return poselib.estimate_generalized_absolute_pose(p2d, p3d, ext, cam_dicts, ransac, {})

    return run


def cpu_ms(fn: Callable[[], object], repeat: int = 500) -> float:
    """Mean CPU time of ``fn`` in ms: excludes the time other processes hold the cores."""
    t0 = time.process_time()
    for _ in range(repeat):
        fn()
    return (time.process_time() - t0) / repeat * 1e3


def against_poselib(ours: Callable[[], object], theirs: Callable[[], object],
                    rounds: int = 7) -> bool:
    """Issue 28's anchor: our estimate + refine + covariance within ``POSELIB_RATIO`` × PoseLib's
    generalized absolute pose (its RANSAC start + refinement; it has no covariance) on the same
    observations, as the ratio of the medians of CPU times measured in alternating rounds."""
    a: list[float] = []
    b: list[float] = []
    for r in range(rounds):
        pair = [(a, ours), (b, theirs)]
        for out, fn in pair if r % 2 == 0 else pair[::-1]:
            out.append(cpu_ms(fn, repeat=200))
    ratio = float(np.median(a) / np.median(b))
    good = ratio <= POSELIB_RATIO
    print(f"  CPU per estimate, alternating rounds: mvpose {np.median(a):.3f} ms, poselib "
          f"{np.median(b):.3f} ms")
    print(f"  target 4 cameras x 8 marks: {ratio:.2f}x PoseLib <= {POSELIB_RATIO:g}x ... "
          f"{'OK' if good else 'MISSED'}", flush=True)
    return good


def main() -> int:
    rng = np.random.default_rng(7)
    ok = True
    for n in (4, 8, 16):
        cams, marks, obs, T_true = lab_scene(n, rng)
        result = estimate_pose(obs, cams, marks, sigma_px=SIGMA_PX)
        rot, trans = transform_error(result.T_rf_from_pf, T_true)
        ours = measure(
            f"mvpose estimate_pose, 4 cameras, {n:2d} marks",
            partial(estimate_pose, obs, cams, marks, sigma_px=SIGMA_PX),
            repeat=1000,
            warmup=WARMUP,
        )
        try:
            run = poselib_call(cams, marks, obs)
            pose, _ = run()
            T_pl = np.eye(4)
            T_pl[:3, :3], T_pl[:3, 3] = pose.R, pose.t
            pl_err = transform_error(T_pl, T_true)
            ref = measure(
                f"poselib estimate_generalized_absolute_pose, {n:2d} marks", run, repeat=300,
                warmup=WARMUP,
            )
        except ImportError:
            ref, pl_err = None, (float("nan"), float("nan"))
        print(ours.line(ref))
        print(
            f"  CPU time per estimate (process_time, less sensitive to other load): "
            f"{cpu_ms(partial(estimate_pose, obs, cams, marks, sigma_px=SIGMA_PX)):.3f} ms"
        )
        if ref is not None:
            print(ref.line())
        print(
            f"  error vs truth: mvpose {rot:.4f}° {trans:.3f} mm ({result.info.initializer}, "
            f"{result.info.iterations} it); poselib {pl_err[0]:.4f}° {pl_err[1]:.3f} mm"
        )
        ok &= check(f"median, {n} marks", ours.median, TARGET_MEDIAN_MS)
        ok &= check(f"p99, {n} marks", ours.p99, TARGET_P99_MS)
        if n == 8 and ref is not None:
            ok &= against_poselib(partial(estimate_pose, obs, cams, marks, sigma_px=SIGMA_PX),
                                  run)
    st = load_station(ROOT / "deploy" / "stations" / "station1.yaml")
    rec = st.recipe()
    cams = view_cameras(st)
    marks = {m.id: np.asarray(m.position, dtype=float) for m in rec.marks}
    obs = synthetic_observations(st, rec, rec.T_rf_from_pf0.matrix, rng, SIGMA_PX)
    info = estimate_pose(obs, cams, marks, sigma_px=SIGMA_PX).info
    t1 = measure(
        "mvpose estimate_pose, station1 (4 fixed, no overlap, 8)",
        lambda: estimate_pose(obs, cams, marks, sigma_px=SIGMA_PX),
        repeat=1000,
        warmup=WARMUP,
    )
    print(t1.line(), f" [{info.initializer}, {info.iterations} it]")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
