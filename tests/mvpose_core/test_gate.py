"""Quality gate: stable reason codes, one test per NOK reason, and measure() end to end."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from estimate_scenes import station

from mvpose_core.estimate import EstimateOptions
from mvpose_core.gate import GateInputs, evaluate_gate
from mvpose_core.measure import measure
from mvpose_core.reasons import Reason
from mvpose_core.station import Tolerances
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import from_robot, transform_error

GOOD = GateInputs(
    marks_used=4,
    converged=True,
    termination="step",
    rms_px=0.2,
    max_residual_px=0.5,
    sigma_rot_deg=0.05,
    sigma_trans_mm=0.3,
    offset_mm=20.0,
    offset_deg=2.0,
)
TOL = Tolerances()


def test_reason_codes_are_stable() -> None:
    # These numbers are on the PLC interface and in stored audit records: never renumber.
    assert {c.name: int(c) for c in Reason if c < 100} == {
        "OK": 0,
        "MARKS_MISSING": 1,
        "NOT_CONVERGED": 2,
        "RESIDUAL_RMS_HIGH": 3,
        "RESIDUAL_MAX_HIGH": 4,
        "ROTATION_UNCERTAINTY_HIGH": 5,
        "TRANSLATION_UNCERTAINTY_HIGH": 6,
        "OFFSET_TRANSLATION_OUT_OF_RANGE": 7,
        "OFFSET_ROTATION_OUT_OF_RANGE": 8,
        "BAD_INPUT": 9,
        "TOO_FEW_MARKS": 10,
        "POSE_NOT_DETERMINED": 11,
        "MARK_BEHIND_CAMERA": 12,
    }


@pytest.mark.parametrize(
    ("change", "code"),
    [
        ({}, Reason.OK),
        ({"marks_used": 3, "missing": ("M4",)}, Reason.MARKS_MISSING),
        ({"converged": False, "termination": "max_iterations"}, Reason.NOT_CONVERGED),
        ({"rms_px": 1.5}, Reason.RESIDUAL_RMS_HIGH),
        ({"max_residual_px": 3.5}, Reason.RESIDUAL_MAX_HIGH),
        ({"sigma_rot_deg": 0.25}, Reason.ROTATION_UNCERTAINTY_HIGH),
        ({"sigma_trans_mm": 1.2}, Reason.TRANSLATION_UNCERTAINTY_HIGH),
        ({"offset_mm": 120.0}, Reason.OFFSET_TRANSLATION_OUT_OF_RANGE),
        ({"offset_deg": 12.0}, Reason.OFFSET_ROTATION_OUT_OF_RANGE),
        ({"sigma_trans_mm": float("nan")}, Reason.TRANSLATION_UNCERTAINTY_HIGH),
        # the most basic cause wins
        ({"marks_used": 3, "rms_px": 9.0, "converged": False}, Reason.MARKS_MISSING),
    ],
)
def test_each_reason(change: dict, code: Reason) -> None:
    v = evaluate_gate(dataclasses.replace(GOOD, **change), TOL, min_marks=4)
    assert v.reason is code and v.ok == (code is Reason.OK)
    if not v.ok:
        assert v.message  # names value and limit
    if code is Reason.RESIDUAL_RMS_HIGH:
        assert "1.500 px exceeds 1 px" in v.message
    if "missing" in change:
        assert "missing: M4" in v.message


@pytest.mark.parametrize("name", ["lab", "station1", "station2"])
def test_measure_returns_true_offsets_and_ok(name: str) -> None:
    st, rec, _, _ = station(name)
    rng = np.random.default_rng(4)
    for _ in range(5):
        T = rec.T_rf_from_pf0.matrix @ random_displacement(rng, 60.0, 5.0)
        obs = synthetic_observations(st, rec, T, rng, rec.detector_noise_px)
        m = measure(st, rec, obs)
        assert m.gate.ok, m.gate
        truth = T @ np.linalg.inv(rec.T_rf_from_pf0.matrix)
        rot, trans = transform_error(from_robot(m.offset, m.convention), truth)
        assert rot < 5 * m.sigma_rot_deg and trans < 5 * m.sigma_trans_mm + 5 * np.radians(
            m.sigma_rot_deg
        ) * np.linalg.norm(rec.T_rf_from_pf0.matrix[:3, 3])
        assert m.marks_missing == () and len(m.marks_used) == len(rec.marks)
        assert m.sigma_posterior is not None
        # the grasp point is 120-150 mm from the part origin: its σ is at least the origin's
        # (at the detector σ the residuals give, mvpose_core.uncertainty.detector_scale)
        assert m.uncertainty is not None
        k2 = (m.uncertainty.detector_noise_px / rec.detector_noise_px) ** 2
        assert m.sigma_trans_mm >= 0.99 * np.sqrt(k2 * np.trace(m.pose.covariance[3:, 3:]))


def test_measure_nok_reasons_end_to_end() -> None:
    st, rec, _, _ = station("lab")
    rng = np.random.default_rng(6)
    T = rec.T_rf_from_pf0.matrix
    obs = synthetic_observations(st, rec, T, rng, rec.detector_noise_px)
    # a mark not found in either camera: still a pose (3 marks), but NOK
    m = measure(st, rec, [o for o in obs if o.mark_id != "M1"])
    assert m.gate.reason is Reason.MARKS_MISSING and m.marks_missing == ("M1",)
    # detection much worse than the recipe's noise model: residual gate
    noisy = synthetic_observations(st, rec, T, rng, 3.0)
    assert measure(st, rec, noisy).gate.reason in (
        Reason.RESIDUAL_RMS_HIGH,
        Reason.RESIDUAL_MAX_HIGH,
    )
    # a noise model too poor for the tolerance: uncertainty gate (a priori, when the station
    # weighs it above the residuals: uncertainty.detector_prior_dof)
    coarse = rec.model_copy(update={"detector_noise_px": 5.0})
    trusting = st.model_copy(update={"uncertainty": st.uncertainty.model_copy(
        update={"detector_prior_dof": 1e6})})
    assert measure(trusting, coarse, obs).gate.reason in (
        Reason.ROTATION_UNCERTAINTY_HIGH,
        Reason.TRANSLATION_UNCERTAINTY_HIGH,
    )
    # the part is further off than the station accepts
    far = T @ random_displacement(np.random.default_rng(1), 0.0, 0.0)
    far[:3, 3] += [0.0, 0.0, 130.0]
    m = measure(st, rec, synthetic_observations(st, rec, far, rng, rec.detector_noise_px))
    assert m.gate.reason is Reason.OFFSET_TRANSLATION_OUT_OF_RANGE
    # the solver stopped early
    st1, rec1, _, _ = station("station1")
    obs1 = synthetic_observations(st1, rec1, rec1.T_rf_from_pf0.matrix, rng, 0.1)
    m = measure(st1, rec1, obs1, options=EstimateOptions(max_iterations=1))
    assert m.gate.reason is Reason.NOT_CONVERGED
