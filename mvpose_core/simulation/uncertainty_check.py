"""Monte Carlo checks of the reported uncertainty: does the 1σ at the grasp point track the error?

Two checks, each on synthetic observations of a station description (no rendering):

- :func:`detector_check`: pixel noise of a chosen σ (not the recipe's a-priori one) on every
  observation; the detector part of the reported 1σ against the actual error;
- :func:`calibration_check`: the station's transforms drawn from their stated 1σ
  (``station.uncertainty``: hand-eye or fixed rig pose, camera in its rig, flange pose at each
  view), the images made with the drawn station and measured with the nominal one; the
  calibration part of the reported 1σ against the actual error.

Errors are taken at the recipe's grasp frame: the rotation angle (deg) and the length of the
translation error (mm); "RMS" is over the trials, "reported" the RMS of the reported 1σ.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mvpose_core.measure import Measurement, measure
from mvpose_core.station import Pose, RecipeConfig, StationConfig
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import Array, make_transform, rotvec_to_matrix, transform_error
from mvpose_core.uncertainty_settings import PoseSigma


@dataclass(frozen=True)
class UncertaintyCheck:
    """Actual RMS error against the RMS reported 1σ, rotation (deg) and translation (mm)."""

    part: str  # "detector" | "calibration"
    trials: int
    actual: tuple[float, float]
    reported: tuple[float, float]

    @property
    def ratio(self) -> tuple[float, float]:
        """reported / actual (1 = the reported 1σ is the RMS error)."""
        return (self.reported[0] / self.actual[0], self.reported[1] / self.actual[1])

    def line(self) -> str:
        r = self.ratio
        return (f"{self.part:<11} {self.trials:5d} trials  actual RMS {self.actual[0]:.5f} deg "
                f"{self.actual[1]:.4f} mm  reported {self.reported[0]:.5f} deg "
                f"{self.reported[1]:.4f} mm  ratio {r[0]:.2f} / {r[1]:.2f}")


def _grasp_error(m: Measurement, T_true: Array, T_pf_from_grasp: Array) -> tuple[float, float]:
    return transform_error(m.T_rf_from_pf @ T_pf_from_grasp, T_true @ T_pf_from_grasp)


def _run(
    part: str, trials: int, one: Callable[[], tuple[Measurement, Array]], recipe: RecipeConfig,
    reported: Callable[[Measurement], tuple[float, float]],
    progress: Callable[[int], Any] | None,
) -> UncertaintyCheck:
    G = recipe.T_pf_from_grasp.matrix
    err = np.empty((trials, 2))
    rep = np.empty((trials, 2))
    for i in range(trials):
        m, T = one()
        err[i] = _grasp_error(m, T, G)
        rep[i] = reported(m)
        if progress is not None:
            progress(1)
    rms = np.sqrt(np.mean(err**2, axis=0))
    rrep = np.sqrt(np.mean(rep**2, axis=0))
    return UncertaintyCheck(part, trials, (float(rms[0]), float(rms[1])),
                            (float(rrep[0]), float(rrep[1])))


def detector_check(
    station: StationConfig, recipe: RecipeConfig, sigma_px: float, trials: int,
    rng: np.random.Generator, *, max_mm: float = 20.0, max_deg: float = 2.0,
    progress: Callable[[int], Any] | None = None,
) -> UncertaintyCheck:
    """Pixel noise N(0, σ²) per coordinate, parts within ±max_mm/±max_deg of the reference."""

    def one() -> tuple[Measurement, Array]:
        T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, max_mm, max_deg)
        return measure(station, recipe, synthetic_observations(station, recipe, T, rng,
                                                               sigma_px)), T

    def reported(m: Measurement) -> tuple[float, float]:
        assert m.uncertainty is not None
        return m.uncertainty.sigma_detector_rot_deg, m.uncertainty.sigma_detector_trans_mm

    return _run("detector", trials, one, recipe, reported, progress)


def _drawn(T: Array, sigma: PoseSigma | None, rng: np.random.Generator) -> Array:
    """``T · Exp(ε)`` with ε drawn from the 1σ (isotropic, as the uncertainty model reads it)."""
    if sigma is None or sigma.is_zero:
        return T
    e = rng.multivariate_normal(np.zeros(6), sigma.covariance())
    return T @ make_transform(rotvec_to_matrix(e[:3]), e[3:])


def drawn_station(
    station: StationConfig, rng: np.random.Generator
) -> tuple[StationConfig, dict[int, Array]]:
    """A station whose rig poses and cameras-in-rig are drawn from ``station.uncertainty``, and
    the flange poses of its views drawn from the robot's repeatability (robot-mounted views)."""
    u = station.uncertainty
    rigs = []
    for rig in station.rigs:
        field = "T_gf_from_rig" if rig.mount == "robot" else "T_rf_from_rig"
        pose = getattr(rig, field)
        cams = [rc.model_copy(update={"T_rig_from_cf": _pose(_drawn(
            rc.T_rig_from_cf.matrix, u.cameras.get(rc.camera), rng))}) for rc in rig.cameras]
        rigs.append(rig.model_copy(update={
            field: _pose(_drawn(pose.matrix, u.rigs.get(rig.id), rng)), "cameras": cams}))
    flanges = {v.id: _drawn(v.T_rf_from_gf.matrix, u.robot_repeatability, rng)
               for v in station.views if v.T_rf_from_gf is not None}
    # model_copy: the drawn values need no validation, and this runs once per trial
    return station.model_copy(update={"rigs": rigs}), flanges


def _pose(T: Array) -> Pose:
    return Pose.from_matrix(T, "matrix")


def calibration_check(
    station: StationConfig, recipe: RecipeConfig, trials: int, rng: np.random.Generator, *,
    sigma_px: float = 0.0, max_mm: float = 20.0, max_deg: float = 2.0,
    progress: Callable[[int], Any] | None = None,
) -> UncertaintyCheck:
    """Images of a drawn station (:func:`drawn_station`), measured with the nominal one."""

    def one() -> tuple[Measurement, Array]:
        T = recipe.T_rf_from_pf0.matrix @ random_displacement(rng, max_mm, max_deg)
        true_station, flanges = drawn_station(station, rng)
        obs = synthetic_observations(true_station, recipe, T, rng, sigma_px, flanges)
        return measure(station, recipe, obs), T

    def reported(m: Measurement) -> tuple[float, float]:
        assert m.uncertainty is not None
        return m.uncertainty.sigma_calibration_rot_deg, m.uncertainty.sigma_calibration_trans_mm

    return _run("calibration", trials, one, recipe, reported, progress)


def with_calibration_sigma(
    station: StationConfig, *, robot: PoseSigma | None = None,
    rigs: PoseSigma | None = None, cameras: PoseSigma | None = None,
) -> StationConfig:
    """The station with the same 1σ for every rig and every non-reference camera in its rig,
    and for the robot's repeatability (robot-mounted stations); others' settings are kept."""
    u = station.uncertainty
    update: dict[str, Any] = {}
    if robot is not None and station.robot_mounted:
        update["robot_repeatability"] = robot
    if rigs is not None:
        update["rigs"] = {r.id: rigs for r in station.rigs}
    if cameras is not None:
        update["cameras"] = {rc.camera: cameras for r in station.rigs for rc in r.cameras[1:]}
    return station.model_copy(update={"uncertainty": u.model_copy(update=update)})


__all__ = ["UncertaintyCheck", "calibration_check", "detector_check", "drawn_station",
           "with_calibration_sigma"]
