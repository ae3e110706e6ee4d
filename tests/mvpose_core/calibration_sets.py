"""Monte Carlo runs of the stereo and fixed-station calibrations on seeded synthetic sets, as the
CLI runs them (each camera's intrinsics from its own images first), with their actual and
reported errors. Shared by test_calibration_uncertainty.py and bench/calibration_uncertainty.py.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mvpose_core.calibration.group import adjust_group
from mvpose_core.calibration.intrinsics import calibrate_intrinsics
from mvpose_core.calibration.station import calibrate_station
from mvpose_core.calibration.stereo import calibrate_stereo
from mvpose_core.calibration.synthetic import make_scene, make_station_scene
from mvpose_core.transforms import compose, invert, transform_error

NOISE_PX = 0.1


@dataclass(frozen=True)
class Run:
    """One calibrated relation: actual error and reported 1σ, (mm, deg) each."""

    error: tuple[float, float]
    sigma: tuple[float, float]
    #: the error of the images-only adjustment started from the true intrinsics (stations)
    reference_error: tuple[float, float] = (float("nan"), float("nan"))
    #: the error with each camera's own intrinsics held (the station before issue 26)
    held_error: tuple[float, float] = (float("nan"), float("nan"))


def _intrinsics(scene_cameras: dict, det: dict, board) -> dict:
    return {
        c: calibrate_intrinsics(c, det[c], board, (cam.width, cam.height)).camera
        for c, cam in scene_cameras.items()
    }


def stereo_run(seed: int, n_poses: int = 15) -> Run:
    """The lab rig (300 mm baseline) at 0.1 px: ``T_cf1_from_cf2`` against the truth."""
    rng = np.random.default_rng(seed)
    scene = make_scene(rng, n_poses=n_poses)
    det = scene.observe(rng, NOISE_PX)
    m = _intrinsics(scene.cameras, det, scene.board)
    res = calibrate_stereo(
        "left", "right", det["left"], det["right"], scene.board, m["left"], m["right"]
    )
    deg, mm = transform_error(invert(res.T_cf2_from_cf1), invert(scene.T_cfc_from_cf0["right"]))
    return Run((mm, deg), (res.sigma_mm, res.sigma_deg))


def station_runs(seed: int, n_placements: int = 12) -> list[Run] | None:
    """Three fixed cameras in a row, board placements measured in RF exactly: each camera's pose
    relative to the first against the truth. None when a camera saw too few placements for
    its own intrinsics (the set cannot be calibrated as the CLI does)."""
    rng = np.random.default_rng(seed)
    scene = make_station_scene(rng, n_placements=n_placements)
    det = scene.observe(rng, NOISE_PX)
    if min(sum(d is not None for d in det[c].values()) for c in det) < 6:
        return None
    m = _intrinsics(scene.cameras, det, scene.board)
    res = calibrate_station(scene.board, m, det, scene.T_rf_from_bf)
    held = calibrate_station(scene.board, m, det, scene.T_rf_from_bf, refine_intrinsics=False)
    found = {c: {s: d for s, d in det[c].items() if d is not None} for c in det}
    ref = adjust_group(scene.board, scene.cameras, found, "cam1")
    truth = scene.T_rf_from_cf
    runs = []
    for c in list(scene.cameras)[1:]:
        true_rel = compose(invert(truth["cam1"]), truth[c])

        def err(T_rf_from_cf: dict, c: str = c, true_rel=true_rel) -> tuple[float, float]:
            deg, mm = transform_error(
                compose(invert(T_rf_from_cf["cam1"]), T_rf_from_cf[c]), true_rel
            )
            return mm, deg

        deg, mm = transform_error(ref.T_ref_from_cf[c], true_rel)
        runs.append(
            Run(err(res.T_rf_from_cf), res.sigma_relative[c], (mm, deg), err(held.T_rf_from_cf))
        )
    return runs


def ratios(runs: list[Run]) -> tuple[float, float]:
    """Actual RMS error over reported RMS 1σ: (translation, rotation)."""
    e = np.array([r.error for r in runs])
    s = np.array([r.sigma for r in runs])
    return tuple(float(x) for x in np.sqrt(np.mean(e**2, axis=0) / np.mean(s**2, axis=0)))  # type: ignore[return-value]


def rms(values: list[tuple[float, float]]) -> tuple[float, float]:
    v = np.array(values)
    return tuple(float(x) for x in np.sqrt(np.mean(v**2, axis=0)))  # type: ignore[return-value]
