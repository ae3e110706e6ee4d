"""Frame offsets: base and tool offsets move the taught grasp onto the measured one; paper eq. 6."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvpose_core.offset import base_frame_offset, frame_offsets, paper_eq6, tool_frame_offset
from mvpose_core.synth import random_displacement
from mvpose_core.transforms import (
    RobotConvention,
    compose,
    from_robot,
    invert,
    make_transform,
    transform_error,
    xyzwpr_to_matrix,
)
from mvpose_core.uncertainty import adjoint, covariance_in_frame, sigma_figures

T_RF_FROM_PF0 = xyzwpr_to_matrix([1650.0, 80.0, -300.0, 0.0, 0.0, 4.0])
T_PF_FROM_GRASP = xyzwpr_to_matrix([300.0, -120.0, 150.0, 180.0, 0.0, 30.0])


def cases() -> list[np.ndarray]:
    rng = np.random.default_rng(9)
    return [T_RF_FROM_PF0 @ random_displacement(rng, 100.0, 10.0) for _ in range(20)]


def test_offsets_move_the_taught_grasp_onto_the_new_one() -> None:
    T_rf_from_g0 = T_RF_FROM_PF0 @ T_PF_FROM_GRASP
    for T in cases():
        T_rf_from_g = T @ T_PF_FROM_GRASP
        delta = base_frame_offset(T, T_RF_FROM_PF0)
        D = tool_frame_offset(T, T_RF_FROM_PF0, T_PF_FROM_GRASP)
        assert transform_error(delta @ T_rf_from_g0, T_rf_from_g) < (1e-9, 1e-9)
        assert transform_error(T_rf_from_g0 @ D, T_rf_from_g) < (1e-9, 1e-9)
        # Δ does not depend on the grasp point: any frame rigid to the part moves with it
        assert transform_error(delta @ T_RF_FROM_PF0, T) < (1e-9, 1e-9)


def test_paper_eq6_is_the_inverse_tool_offset() -> None:
    # CF1: any camera fixed during the measurement (paper: first camera of the first view).
    T_rf_from_cf1 = xyzwpr_to_matrix([1400.0, 40.0, 850.0, 172.0, 0.0, -90.0])
    T_rf_from_g0 = T_RF_FROM_PF0 @ T_PF_FROM_GRASP
    for T in cases():
        T_cf1_from_pf0 = invert(T_rf_from_cf1) @ T_RF_FROM_PF0
        T_cf1_from_pfi = invert(T_rf_from_cf1) @ T
        paper = paper_eq6(T_cf1_from_pf0, T_cf1_from_pfi, T_PF_FROM_GRASP)
        D = tool_frame_offset(T, T_RF_FROM_PF0, T_PF_FROM_GRASP)
        assert np.allclose(paper, invert(D), atol=1e-9)
        delta = base_frame_offset(T, T_RF_FROM_PF0)
        assert np.allclose(delta, T_rf_from_g0 @ invert(paper) @ invert(T_rf_from_g0), atol=1e-9)
        # eq. 5 in the paper's orientation: T_gfi_from_rf = Δ_paper · T_gf0_from_rf
        assert np.allclose(invert(T @ T_PF_FROM_GRASP), paper @ invert(T_rf_from_g0), atol=1e-9)


def test_pure_translation_example() -> None:
    T = make_transform(np.eye(3), [10.0, -5.0, 2.0]) @ T_RF_FROM_PF0
    off = frame_offsets(T, T_RF_FROM_PF0, T_PF_FROM_GRASP, "fanuc")
    assert np.allclose(off.base, [10.0, -5.0, 2.0, 0.0, 0.0, 0.0], atol=1e-9)
    R_g0 = (T_RF_FROM_PF0 @ T_PF_FROM_GRASP)[:3, :3]
    assert np.allclose(off.tool[:3], R_g0.T @ [10.0, -5.0, 2.0], atol=1e-9)
    assert abs(off.grasp_displacement_mm - np.linalg.norm([10.0, -5.0, 2.0])) < 1e-9
    assert off.rotation_deg < 1e-9


def test_zero_offset() -> None:
    off = frame_offsets(T_RF_FROM_PF0, T_RF_FROM_PF0, T_PF_FROM_GRASP, "kuka")
    assert np.allclose(off.base, 0.0, atol=1e-9) and np.allclose(off.tool, 0.0, atol=1e-9)


@pytest.mark.parametrize("conv", list(RobotConvention))
def test_offsets_in_every_convention_round_trip(conv: RobotConvention) -> None:
    for T in cases()[:5]:
        off = frame_offsets(T, T_RF_FROM_PF0, T_PF_FROM_GRASP, conv)
        assert transform_error(from_robot(off.base, conv), off.T_rf_offset) < (1e-9, 1e-9)
        assert transform_error(from_robot(off.tool, conv), off.T_tool_offset) < (1e-9, 1e-9)


def test_covariance_at_the_grasp_point_includes_the_lever_arm() -> None:
    # A right perturbation of PF is the adjoint-mapped perturbation of the grasp frame.
    rng = np.random.default_rng(3)
    delta = np.r_[rng.normal(0, 1e-6, 3), rng.normal(0, 1e-4, 3)]  # first order: tiny δ
    Exp = make_transform(Rotation.from_rotvec(delta[:3]).as_matrix(), delta[3:])
    left = T_RF_FROM_PF0 @ Exp @ T_PF_FROM_GRASP
    d_g = adjoint(invert(T_PF_FROM_GRASP)) @ delta
    right = (
        T_RF_FROM_PF0
        @ T_PF_FROM_GRASP
        @ make_transform(Rotation.from_rotvec(d_g[:3]).as_matrix(), d_g[3:])
    )
    assert transform_error(left, right)[1] < 1e-8  # vs ~4e-4 mm of lever-arm motion
    # 0.1° rotation about z at the part origin, no translation: 0.1° × lever arm at the grasp
    cov = np.diag([0.0, 0.0, np.radians(0.1) ** 2, 0.0, 0.0, 0.0])
    rot, trans = sigma_figures(covariance_in_frame(cov, T_PF_FROM_GRASP))
    lever = np.linalg.norm(T_PF_FROM_GRASP[:2, 3])
    assert abs(rot - 0.1) < 1e-12 and abs(trans - np.radians(0.1) * lever) < 1e-9
    assert np.allclose(covariance_in_frame(cov, compose(np.eye(4))), cov)
