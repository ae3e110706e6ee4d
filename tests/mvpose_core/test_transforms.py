"""Transforms: frame convention, rotations, robot conventions against published values and scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mvpose_core.transforms import (
    RobotConvention,
    apply,
    check_transform,
    compose,
    from_robot,
    invert,
    make_transform,
    matrix_to_quat_wxyz,
    matrix_to_xyzwpr,
    matrix_to_zyx,
    quat_wxyz_to_matrix,
    to_robot,
    transform_error,
    xyzwpr_to_matrix,
    zyx_to_matrix,
)


def random_transform(rng: np.random.Generator) -> np.ndarray:
    return make_transform(
        Rotation.random(random_state=rng).as_matrix(), rng.uniform(-2000, 2000, 3)
    )


def test_compose_and_invert_follow_frame_names() -> None:
    rng = np.random.default_rng(1)
    T_b_from_a, T_c_from_b = random_transform(rng), random_transform(rng)
    p_a = rng.normal(size=(5, 3)) * 100
    p_c = apply(compose(T_c_from_b, T_b_from_a), p_a)
    assert np.allclose(p_c, apply(T_c_from_b, apply(T_b_from_a, p_a)))
    assert np.allclose(apply(invert(T_b_from_a), apply(T_b_from_a, p_a)), p_a)
    assert np.allclose(compose(T_b_from_a, invert(T_b_from_a)), np.eye(4))


def test_check_transform_rejects_bad_matrices() -> None:
    with pytest.raises(ValueError, match="4x4"):
        check_transform(np.eye(3), "T_rf_from_pf")
    bad = np.eye(4)
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        check_transform(bad, "T_rf_from_pf")
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="proper rotation"):
        check_transform(mirror)


def test_check_transform_judges_as_np_allclose_and_det() -> None:
    """Its rotation and last-row tests give the verdicts of np.allclose (atol = tol, rtol 1e-5)
    and np.linalg.det, near the tolerance's edge from both sides."""
    rng = np.random.default_rng(3)
    verdicts = set()
    for k in range(400):
        T = random_transform(rng)
        T[:3, :3] *= 1.0 + rng.choice([-1, 1]) * rng.uniform(0.0, 1.2e-5)  # around the edge
        if k % 4 == 1:
            T[:3, :3] += rng.normal(0.0, 3e-7, (3, 3))
        if k % 4 == 2:
            T[3, rng.integers(4)] += rng.choice([-1, 1]) * rng.uniform(0.0, 2e-5)
        if k % 4 == 3:
            T[:3, 2] *= -1.0  # a mirror
        R = T[:3, :3]
        expected = (np.allclose(R @ R.T, np.eye(3), atol=1e-6) and np.linalg.det(R) >= 0
                    and np.allclose(T[3], [0, 0, 0, 1], atol=1e-6))
        try:
            check_transform(T)
            got = True
        except ValueError:
            got = False
        assert got == expected, (k, T)
        verdicts.add(got)
    assert verdicts == {True, False}


# Published/hand-derivable examples: (convention, pose vector, expected rotation matrix).
_QUARTER_Z = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
_HALF_X = np.diag([1.0, -1.0, -1.0])
PUBLISHED = [
    # FANUC: W=180 flips the tool to point down (the usual "tool down" pose, W P R = 180 0 0).
    ("fanuc", [100, 200, 300, 180, 0, 0], _HALF_X),
    # FANUC: R is the rotation about the base z axis.
    ("fanuc", [0, 0, 0, 0, 0, 90], _QUARTER_Z),
    ("yaskawa", [0, 0, 0, 180, 0, 0], _HALF_X),
    # KUKA: A about z first (Z-Y'-X''), A=90 is a quarter turn about z.
    ("kuka", [0, 0, 0, 90, 0, 0], _QUARTER_Z),
    ("kuka", [0, 0, 0, 0, 0, 180], _HALF_X),
    # ABB RAPID orient [0.70711, 0, 0, 0.70711] is 90° about z; [0, 1, 0, 0] is 180° about x.
    ("abb", [0, 0, 0, np.sqrt(0.5), 0, 0, np.sqrt(0.5)], _QUARTER_Z),
    ("abb", [0, 0, 0, 0, 1, 0, 0], _HALF_X),
    # UR: p[x, y, z, rx, ry, rz] with a rotation vector in rad; [0, 0, π/2] is 90° about z.
    ("ur", [0, 0, 0, 0, 0, np.pi / 2], _QUARTER_Z),
    ("ur", [0.1, 0.2, 0.3, np.pi, 0, 0], _HALF_X),
]


@pytest.mark.parametrize(("conv", "values", "R"), PUBLISHED)
def test_published_examples(conv: str, values: list[float], R: np.ndarray) -> None:
    T = from_robot(values, conv)
    assert np.allclose(T[:3, :3], R, atol=1e-9)
    scale = 1000.0 if conv == "ur" else 1.0
    assert np.allclose(T[:3, 3], np.asarray(values[:3]) * scale)


def test_ur_translation_is_metres() -> None:
    T = from_robot([0.1, -0.2, 0.3, 0, 0, 0], "ur")
    assert np.allclose(T[:3, 3], [100.0, -200.0, 300.0])
    assert np.allclose(to_robot(T, "ur")[:3], [0.1, -0.2, 0.3])


def test_euler_conventions_match_scipy() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        w, p, r = rng.uniform(-179, 179), rng.uniform(-89, 89), rng.uniform(-179, 179)
        # FANUC W P R = fixed-axis x-y-z = scipy extrinsic "xyz".
        R_ref = Rotation.from_euler("xyz", [w, p, r], degrees=True).as_matrix()
        assert np.allclose(xyzwpr_to_matrix([0, 0, 0, w, p, r])[:3, :3], R_ref, atol=1e-12)
        # KUKA A B C = intrinsic Z-Y'-X'' = scipy "ZYX".
        R_kuka = Rotation.from_euler("ZYX", [w, p, r], degrees=True).as_matrix()
        assert np.allclose(from_robot([0, 0, 0, w, p, r], "kuka")[:3, :3], R_kuka, atol=1e-12)
        q = Rotation.from_matrix(R_ref).as_quat(scalar_first=True)
        q = q if q[0] >= 0 else -q
        assert np.allclose(matrix_to_quat_wxyz(R_ref), q, atol=1e-12)


@pytest.mark.parametrize("conv", list(RobotConvention))
def test_every_convention_round_trips(conv: RobotConvention) -> None:
    rng = np.random.default_rng(3)
    for _ in range(100):
        T = random_transform(rng)
        v = to_robot(T, conv)
        assert v.shape == (conv.size,)
        back = from_robot(v, conv)
        rot, trans = transform_error(back, T)
        assert rot < 1e-9 and trans < 1e-9
        # and the vector itself is stable (canonical form)
        assert np.allclose(to_robot(back, conv), v, atol=1e-9)


@pytest.mark.parametrize("pitch", [90.0, -90.0])
def test_gimbal_lock_is_unique_and_round_trips(pitch: float) -> None:
    for r, w in [(30.0, 0.0), (10.0, 20.0), (-170.0, 45.0)]:
        T = xyzwpr_to_matrix([1, 2, 3, w, pitch, r])
        v = matrix_to_xyzwpr(T)
        assert v[3] == 0.0  # W set to 0 at the lock
        assert abs(v[4] - pitch) < 1e-6
        assert np.allclose(xyzwpr_to_matrix(v), T, atol=1e-9)


def test_zyx_ranges() -> None:
    rng = np.random.default_rng(4)
    for _ in range(200):
        z, y, x = matrix_to_zyx(Rotation.random(random_state=rng).as_matrix())
        assert -90 <= y <= 90 and -180 <= z <= 180 and -180 <= x <= 180


def test_from_robot_names_bad_values() -> None:
    with pytest.raises(ValueError, match="abb pose has 7 values"):
        from_robot([0, 0, 0, 1, 0, 0], "abb")
    with pytest.raises(ValueError, match="NaN"):
        from_robot([0, 0, np.nan, 0, 0, 0], "fanuc")
    with pytest.raises(ValueError, match="zero or non-finite norm"):
        quat_wxyz_to_matrix([0, 0, 0, 0])
    with pytest.raises(ValueError):
        from_robot([0] * 6, "staubli")


def test_transform_error_measures_angle_and_distance() -> None:
    T = make_transform(zyx_to_matrix(0.5, 0, 0), [3.0, 4.0, 0.0])
    rot, trans = transform_error(T, np.eye(4))
    assert abs(rot - 0.5) < 1e-9 and abs(trans - 5.0) < 1e-12


def test_conventions_doc_examples_run() -> None:
    """The Python blocks in docs/conventions.md run in order and their asserts hold."""
    import re
    from pathlib import Path

    doc = Path(__file__).resolve().parents[2] / "docs" / "conventions.md"
    blocks = re.findall(r"```python\n(.*?)```", doc.read_text(encoding="utf-8"), re.S)
    assert len(blocks) >= 4
    namespace: dict[str, object] = {}
    for block in blocks:
        exec(compile(block, str(doc), "exec"), namespace)  # noqa: S102 - our own documentation
