"""The reported 1σ tracks the real error: detector part from the residuals, calibration part
propagated from the station's stated 1σ — each against a Monte Carlo on a deploy/ station."""

from __future__ import annotations

from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pytest

from mvpose_core.calibration.files import (
    InputsSummary,
    RigCalibration,
    apply_calibration,
    make_calibration,
    pose,
)
from mvpose_core.measure import measure
from mvpose_core.reasons import Reason
from mvpose_core.scene import view_cameras
from mvpose_core.simulation.uncertainty_check import (
    calibration_check,
    detector_check,
    with_calibration_sigma,
)
from mvpose_core.station import Pose, StationConfig, load_station
from mvpose_core.synth import synthetic_observations
from mvpose_core.transforms import make_transform, rotvec_to_matrix, transform_error
from mvpose_core.uncertainty import (
    calibration_covariance,
    calibration_terms,
    detector_scale,
)
from mvpose_core.uncertainty_settings import PoseSigma

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"
CALIB = {"robot": PoseSigma(mm=0.02, deg=0.004), "rigs": PoseSigma(mm=0.1, deg=0.015),
         "cameras": PoseSigma(mm=0.03, deg=0.003)}


def station(name: str) -> StationConfig:
    return load_station(STATIONS / f"{name}.yaml")


def test_detector_scale_pools_residuals_with_the_prior() -> None:
    assert detector_scale(0.9, 10, 0.0) == pytest.approx(0.09)  # the residuals alone
    assert detector_scale(0.9, 10, 10.0) == pytest.approx((10 + 0.9) / 20)
    assert detector_scale(0.0, 0, 0.0) == 1.0  # no degrees of freedom: the a-priori σ
    assert detector_scale(0.9, 10, 1e12) == pytest.approx(1.0)


@pytest.mark.parametrize("name", ["lab", "station2"])
def test_detector_part_tracks_the_error_at_a_noise_unlike_the_prior(name: str) -> None:
    st = station(name)
    rec = st.recipe()
    assert rec.detector_noise_px == 0.1  # the a-priori σ is 5x the true one below
    chk = detector_check(st, rec, 0.02, 150, np.random.default_rng(11))
    for r in chk.ratio:
        assert 0.7 <= r <= 1.4, chk.line()
    # the a-priori σ alone (the old report) would have been 5x too pessimistic
    prior = st.model_copy(update={"uncertainty": st.uncertainty.model_copy(
        update={"detector_prior_dof": 1e9})})
    old = detector_check(prior, rec, 0.02, 20, np.random.default_rng(11))
    assert min(old.ratio) > 3.0, old.line()


@pytest.mark.parametrize("name", ["lab", "station1"])
def test_calibration_part_tracks_the_error_of_a_drawn_calibration(name: str) -> None:
    st = with_calibration_sigma(station(name), **CALIB)
    chk = calibration_check(st, st.recipe(), 150, np.random.default_rng(5))
    for r in chk.ratio:
        assert 0.7 <= r <= 1.4, chk.line()


def test_calibration_covariance_is_the_estimators_own_first_order_response() -> None:
    """For a small hand-eye error along one axis, the predicted covariance is vvᵀ with v the
    pose's actual change when the images come from the changed station."""
    st = with_calibration_sigma(station("lab"), rigs=PoseSigma(mm=1.0, deg=1.0))
    rec = st.recipe()
    T = rec.T_rf_from_pf0.matrix
    cams = view_cameras(st)
    marks = {m.id: np.asarray(m.position, dtype=float) for m in rec.marks}
    obs = synthetic_observations(st, rec, T, np.random.default_rng(0), 0.0)
    (term,) = calibration_terms(st, cams)
    rig = st.rigs[0]
    assert rig.T_gf_from_rig is not None
    for axis, h in ((0, 1e-4), (2, 1e-4), (3, 0.02), (5, 0.02)):
        unit = np.zeros((6, 6))
        unit[axis, axis] = h * h
        one = [replace(term, covariance=unit)]
        cov, _ = calibration_covariance(cams, marks, [o.key for o in obs],
                                        np.full(len(obs), 10.0), T, one)
        e = np.zeros(6)
        e[axis] = h
        X = rig.T_gf_from_rig.matrix @ make_transform(rotvec_to_matrix(e[:3]), e[3:])
        moved = st.model_copy(update={"rigs": [rig.model_copy(
            update={"T_gf_from_rig": Pose.from_matrix(X, "matrix")})]})
        m = measure(st, rec, synthetic_observations(moved, rec, T, np.random.default_rng(0), 0.0))
        d = np.linalg.inv(T) @ m.T_rf_from_pf
        dv = np.concatenate([[d[2, 1], d[0, 2], d[1, 0]], d[:3, 3]])  # δ to first order
        assert np.allclose(np.outer(dv, dv), cov, rtol=0.05, atol=1e-4 * np.abs(cov).max())


def test_no_calibration_sigma_means_no_calibration_part() -> None:
    st = station("station1")
    rec = st.recipe()
    obs = synthetic_observations(st, rec, rec.T_rf_from_pf0.matrix, np.random.default_rng(2), 0.05)
    m = measure(st, rec, obs)
    u = m.uncertainty
    assert u is not None and u.calibration_terms == {}
    assert u.sigma_calibration_trans_mm == 0.0 and u.sigma_calibration_rot_deg == 0.0
    assert m.sigma_trans_mm == pytest.approx(u.sigma_detector_trans_mm)
    assert 0.02 < u.detector_noise_px < 0.1 and u.detector_dof == 2 * len(obs) - 6


def test_gate_judges_both_parts_together() -> None:
    st = station("station1")
    rec = st.recipe()
    obs = synthetic_observations(st, rec, rec.T_rf_from_pf0.matrix, np.random.default_rng(2), 0.02)
    assert measure(st, rec, obs).gate.ok
    shaky = with_calibration_sigma(st, rigs=PoseSigma(mm=1.5, deg=0.05))
    m = measure(shaky, rec, obs)
    assert m.uncertainty is not None and m.uncertainty.sigma_calibration_trans_mm > 1.0
    assert m.gate.reason is Reason.TRANSLATION_UNCERTAINTY_HIGH
    assert "pose of fixed rig cell" in m.uncertainty.calibration_terms
    assert m.sigma_trans_mm**2 == pytest.approx(
        m.uncertainty.sigma_detector_trans_mm**2 + m.uncertainty.sigma_calibration_trans_mm**2,
        rel=0.05)  # uncorrelated parts: close to a sum of squares at the grasp point


def test_hand_eye_sigma_comes_from_the_calibration_report() -> None:
    st = station("lab")
    rig = st.rigs[0]
    assert rig.T_gf_from_rig is not None
    calib = make_calibration(
        "handeye", InputsSummary(board="chessboard:11x8:35"),
        rigs={rig.id: RigCalibration(T_gf_from_rig=pose(rig.T_gf_from_rig.matrix))},
        report={"handeye (robot)": {"sigma": {
            "T_gf_from_cf translation mm": 0.16, "T_gf_from_cf rotation deg": 0.03,
            "detector noise px (from residuals)": 0.05,
            "T_gf_from_cf translation mm (jackknife)": 1.3,
            "T_gf_from_cf rotation deg (jackknife)": 0.01}}},
        station=st.name, created=datetime(2026, 11, 23, tzinfo=UTC),
    )
    applied = apply_calibration(st, calib)
    assert applied.uncertainty.rigs == {rig.id: PoseSigma(mm=1.3, deg=0.03)}
    rec = applied.recipe()
    obs = synthetic_observations(applied, rec, rec.T_rf_from_pf0.matrix,
                                 np.random.default_rng(1), 0.02)
    u = measure(applied, rec, obs).uncertainty
    assert u is not None and set(u.calibration_terms) == {f"hand-eye {rig.id}"}
    assert u.sigma_calibration_trans_mm > 0.5


def test_transform_error_helper_matches_grasp_error() -> None:
    # the checks take errors at the grasp frame: a pure rotation about the part origin moves
    # the grasp point by the lever arm
    st = station("lab")
    rec = st.recipe()
    G = rec.T_pf_from_grasp.matrix
    T = rec.T_rf_from_pf0.matrix
    R = make_transform(rotvec_to_matrix([0.0, 0.0, 1e-3]), [0.0, 0.0, 0.0])
    _, mm = transform_error(T @ R @ G, T @ G)
    assert mm == pytest.approx(1e-3 * np.linalg.norm(G[:2, 3]), rel=1e-3)
