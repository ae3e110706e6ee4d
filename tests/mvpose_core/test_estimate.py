"""Pose estimator: Jacobian, optimality at the truth, convergence on every example station."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from estimate_scenes import NAMES, noiseless, station

from mvpose_core.estimate import EstimateOptions, Observation, estimate_pose, pack_layout
from mvpose_core.refine import Packed, levenberg_marquardt, residuals_and_jacobian, so3_exp
from mvpose_core.synth import random_displacement, synthetic_observations
from mvpose_core.transforms import make_transform, transform_error
from mvpose_core.triangulate import triangulate_marks
from mvpose_core.uncertainty import cramer_rao_covariance


def packed_with_uv(name: str, rational: bool = False) -> tuple[Packed, np.ndarray]:
    obs, cams, marks, T = noiseless(name)
    pk, _ = pack_layout(cams, marks, [o.key for o in obs])
    k = pk.k.copy()
    if rational:  # exercise OpenCV's rational terms too
        k[:, 5:] = [0.05, -0.01, 0.003]
    pk = Packed(
        pk.R_cf_from_rf,
        pk.t_cf_from_rf,
        pk.p_pf,
        np.array([o.uv for o in obs]),
        pk.weight,
        pk.f,
        pk.c,
        k,
        rational,
    )
    return pk, T


def perturbed(T: np.ndarray, delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of T · Exp(δ) with δ = (ω, v) — the documented right perturbation."""
    R = T[:3, :3] @ so3_exp(delta[:3])
    t = T[:3, 3] + T[:3, :3] @ delta[3:]
    return R, t


@pytest.mark.parametrize("name", NAMES)
def test_packed_projection_matches_camera_model(name: str) -> None:
    obs, cams, marks, T = noiseless(name)
    pk, _ = pack_layout(cams, marks, [o.key for o in obs])
    res, _, _ = residuals_and_jacobian(pk, T[:3, :3], T[:3, 3])
    by_key = {(c.view, c.camera_id): c for c in cams}
    for o, r in zip(obs, res, strict=True):
        cam = by_key[(o.view, o.camera_id)]
        p_cf = np.linalg.inv(cam.T_rf_from_cf) @ T @ np.append(marks[o.mark_id], 1.0)
        assert np.allclose(-r, cam.model.project(p_cf[None, :3])[0], atol=1e-9)


@pytest.mark.parametrize(
    ("name", "rational"), [("lab", False), ("station1", True), ("station2", False)]
)
def test_jacobian_matches_finite_differences(name: str, rational: bool) -> None:
    pk, T = packed_with_uv(name, rational)
    rng = np.random.default_rng(5)
    R0, t0 = perturbed(T, np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 20, 3)])
    T0 = make_transform(R0, t0)
    res0, J, _ = residuals_and_jacobian(pk, R0, t0)
    for a, h in enumerate([1e-6] * 3 + [1e-3] * 3):
        d = np.zeros(6)
        d[a] = h
        rp, _, _ = residuals_and_jacobian(pk, *perturbed(T0, d))
        rm, _, _ = residuals_and_jacobian(pk, *perturbed(T0, -d))
        fd = -(rp - rm) / (2 * h)  # J is of the predicted pixels; residual = observed − predicted
        scale = np.max(np.abs(J[:, :, a]))
        assert np.max(np.abs(J[:, :, a] - fd)) < 1e-6 * scale, f"column {a}"


@pytest.mark.parametrize("name", NAMES)
def test_residual_and_gradient_vanish_at_truth(name: str) -> None:
    pk, T = packed_with_uv(name)
    res, J, depth = residuals_and_jacobian(pk, T[:3, :3], T[:3, 3])
    assert np.max(np.abs(res)) < 1e-8
    assert np.all(depth > 500)
    g = J.reshape(-1, 6).T @ res.reshape(-1)
    assert np.max(np.abs(g)) < 1e-6
    # and LM started at the truth stops at once without moving
    lm = levenberg_marquardt(pk, T[:3, :3], T[:3, 3])
    assert lm.converged and lm.iterations == 1
    assert transform_error(make_transform(lm.R, lm.t), T) < (1e-9, 1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_converges_from_initial_estimate_for_random_displacements(name: str) -> None:
    st, rec, cams, marks = station(name)
    rng = np.random.default_rng(11)
    for _ in range(40):
        T = rec.T_rf_from_pf0.matrix @ random_displacement(rng, 100.0, 10.0)
        obs = synthetic_observations(st, rec, T, rng, 0.0, require_in_image=False)
        r = estimate_pose(obs, cams, marks)
        assert r.info.converged, r.info
        rot, trans = transform_error(r.T_rf_from_pf, T)
        assert rot < 1e-7 and trans < 1e-5, (rot, trans, r.info)
        assert r.info.rms_px < 1e-6
        # with detector noise the estimate stays within a few σ of the bound
        noisy = synthetic_observations(st, rec, T, rng, 0.5, require_in_image=False)
        rn = estimate_pose(noisy, cams, marks, sigma_px=0.5)
        assert rn.info.converged
        rot, trans = transform_error(rn.T_rf_from_pf, T)
        sig_rot = np.degrees(np.sqrt(np.trace(rn.covariance[:3, :3])))
        sig_trans = np.sqrt(np.trace(rn.covariance[3:, 3:]))
        assert rot < 5 * sig_rot and trans < 5 * sig_trans


def test_initializer_follows_the_layout() -> None:
    obs, cams, marks, T = noiseless("lab")
    assert estimate_pose(obs, cams, marks).info.initializer == "triangulation"
    obs, cams, marks, T = noiseless("station1")
    assert estimate_pose(obs, cams, marks).info.initializer == "generalized_dlt"
    # 4 single observations: no triangulation, too few rays for the DLT: only a prior starts it
    few = obs[:4] + obs[6:7]
    with pytest.raises(ValueError, match="no start for the pose"):
        estimate_pose(few, cams, marks)
    prior = T @ make_transform(so3_exp(np.radians([2.0, -1.0, 1.5])), [20.0, -30.0, 10.0])
    r = estimate_pose(few, cams, marks, initial_T_rf_from_pf=prior)
    assert r.info.initializer == "prior"
    assert transform_error(r.T_rf_from_pf, T) < (1e-6, 1e-4)


def test_triangulation_recovers_marks_with_small_residuals() -> None:
    obs, cams, marks, T = noiseless("lab")
    tri = triangulate_marks(obs, cams)
    assert set(tri.mark_ids) == set(marks)
    for m, p in zip(tri.mark_ids, tri.points_rf, strict=True):
        assert np.linalg.norm(p - (T[:3, :3] @ marks[m] + T[:3, 3])) < 1e-6
    assert np.all(tri.residual_px < 1e-6) and np.all(tri.n_rays == 2)
    noisy = synthetic_observations(*station("lab")[:2], T, np.random.default_rng(1), 1.0)
    tri = triangulate_marks(noisy, cams)
    assert np.all(tri.residual_px > 0.01) and np.all(tri.residual_px < 5)


def test_left_only_objective_uses_first_camera_of_each_rig() -> None:
    obs, cams, marks, T = noiseless("lab")
    r = estimate_pose(obs, cams, marks, EstimateOptions(objective="left_only"))
    assert [o.camera_id for o, u in zip(obs, r.used, strict=True) if u] == ["left"] * 4
    assert transform_error(r.T_rf_from_pf, T) < (1e-7, 1e-5)
    assert r.residuals_px.shape == (len(obs), 2)
    both = estimate_pose(obs, cams, marks)
    # fewer observations, larger covariance
    assert np.trace(r.covariance[3:, 3:]) > 1.5 * np.trace(both.covariance[3:, 3:])


def test_covariance_is_the_cramer_rao_bound_at_the_solution() -> None:
    obs, cams, marks, T = noiseless("lab")
    r = estimate_pose(obs, cams, marks, sigma_px=0.7)
    crb = cramer_rao_covariance(cams, marks, [o.key for o in obs], T, 0.7)
    assert np.allclose(r.covariance, crb, rtol=1e-6, atol=1e-15)
    crb_left = cramer_rao_covariance(cams, marks, [o.key for o in obs], T, 0.7, "left_only")
    assert np.trace(crb_left) > np.trace(crb)


def test_outlier_rule_rejects_the_gross_error() -> None:
    st, rec, cams, marks = station("lab")
    T = rec.T_rf_from_pf0.matrix
    obs = synthetic_observations(st, rec, T, np.random.default_rng(2), 0.3)
    bad = obs[5]
    obs[5] = Observation(bad.view, bad.camera_id, bad.mark_id, bad.uv + [35.0, -20.0])
    plain = estimate_pose(obs, cams, marks, sigma_px=0.3)
    robust = estimate_pose(obs, cams, marks, EstimateOptions(outlier_px=3.0), sigma_px=0.3)
    huber = estimate_pose(
        obs, cams, marks, EstimateOptions(loss="huber", huber_px=1.0), sigma_px=0.3
    )
    assert robust.info.rejected == (bad.key,)
    assert not robust.used[5] and robust.used.sum() == len(obs) - 1
    assert np.linalg.norm(robust.residuals_px[5]) > 30  # still reported, against the final pose
    e_plain = transform_error(plain.T_rf_from_pf, T)
    e_robust = transform_error(robust.T_rf_from_pf, T)
    e_huber = transform_error(huber.T_rf_from_pf, T)
    assert e_robust[1] < 0.5 * e_plain[1] and e_huber[1] < e_plain[1]
    assert plain.info.rejected == ()


def test_warm_start_is_tried_first_and_a_bad_one_is_replaced() -> None:
    obs, cams, marks, T = noiseless("station1")
    near = T @ make_transform(so3_exp(np.radians([0.3, 0.0, -0.2])), [2.0, 1.0, -3.0])
    r = estimate_pose(obs, cams, marks, warm_start=near)
    assert r.info.initializer == "warm_start"
    assert transform_error(r.T_rf_from_pf, T) < (1e-7, 1e-5)
    # a warm start 3 m off ends in a poor minimum: the layout's own start takes over
    far = T @ make_transform(np.eye(3), [0.0, 0.0, 3000.0])
    r = estimate_pose(obs, cams, marks, warm_start=far)
    assert r.info.initializer == "generalized_dlt"
    assert transform_error(r.T_rf_from_pf, T) < (1e-7, 1e-5)


@pytest.mark.parametrize("name", NAMES)
def test_default_step_tolerance_stops_a_negligible_distance_from_full_convergence(
    name: str,
) -> None:
    # EstimateOptions.step_tol stops when the next step is < 0.03 σ and applies it from the
    # linear model: the pose must then be within 1e-3 σ of the one LM reaches when run to the
    # end (measured in the estimate's own covariance; a looser tolerance saves an evaluation).
    st, rec, cams, marks = station(name)
    rng = np.random.default_rng(5)
    for _ in range(20):
        T = rec.T_rf_from_pf0.matrix @ random_displacement(rng, 100.0, 10.0)
        obs = synthetic_observations(st, rec, T, rng, 0.5, require_in_image=False)
        fast = estimate_pose(obs, cams, marks, sigma_px=0.5)
        full = estimate_pose(obs, cams, marks, EstimateOptions(step_tol=1e-9), sigma_px=0.5)
        assert full.info.iterations >= fast.info.iterations
        dT = np.linalg.inv(fast.T_rf_from_pf) @ full.T_rf_from_pf  # right perturbation
        d = np.concatenate([[dT[2, 1], dT[0, 2], dT[1, 0]], dT[:3, 3]])
        assert float(d @ np.linalg.solve(fast.covariance, d)) ** 0.5 < 1e-3


@pytest.mark.parametrize(("name", "rational"), [("lab", False), ("station1", True)])
def test_one_lens_projection_matches_the_general_path(name: str, rational: bool) -> None:
    """Rows sharing one lens project through cv2.projectPoints; the numpy model gives the same."""
    pk, T = packed_with_uv(name, rational)
    f, c, k = pk.f[0], pk.c[0], pk.k[0]
    assert np.all(pk.f == f) and np.all(pk.c == c) and np.all(pk.k == k)
    K = np.array([[f[0], 0.0, c[0]], [0.0, f[1], c[1]], [0.0, 0.0, 1.0]])
    with_lens = replace(pk, lens=(K, k if rational else k[:5]))
    rng = np.random.default_rng(3)
    R, t = perturbed(T, np.r_[rng.normal(0, 0.02, 3), rng.normal(0, 20, 3)])
    for a, b in zip(
        residuals_and_jacobian(pk, R, t), residuals_and_jacobian(with_lens, R, t), strict=True
    ):
        assert np.allclose(a, b, rtol=1e-9, atol=1e-9 * np.max(np.abs(a)))
    assert not np.allclose(residuals_and_jacobian(pk, R, t)[0], 0.0)
    assert with_lens.subset(np.arange(3)).lens is with_lens.lens


@pytest.mark.parametrize("name", NAMES)
def test_refinement_information_is_jtwj_at_its_jacobian(name: str) -> None:
    """The covariance reuses the refinement's own JᵀWJ: it must be the one at ``jacobian``."""
    pk, T = packed_with_uv(name)
    rng = np.random.default_rng(5)
    noisy = pk.with_measurements(pk.uv + rng.normal(0, 0.5, pk.uv.shape), np.full(pk.n, 2.0))
    start = perturbed(T, np.array([0.01, -0.02, 0.01, 3.0, -2.0, 4.0]))
    uneven = noisy.with_measurements(noisy.uv, rng.uniform(0.5, 3.0, pk.n))
    for p in (noisy, uneven):
        lm = levenberg_marquardt(p, *start)
        assert lm.information is not None
        Jw = lm.jacobian.reshape(-1, 6) * np.repeat(p.weight, 2)[:, None]
        expected = Jw.T @ Jw
        scale = np.abs(expected).max()
        assert np.allclose(lm.information, expected, rtol=1e-12, atol=1e-12 * scale)
    # a robust loss's H carries the IRLS weights: no information then
    assert levenberg_marquardt(noisy, *start, loss="huber", huber_px=0.3).information is None
