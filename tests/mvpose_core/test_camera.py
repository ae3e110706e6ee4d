"""Camera model: identical to cv2.projectPoints, analytic Jacobian, undistortion round trip."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mvpose_core.camera import CameraModel, check_in_front

DISTORTIONS = [
    (0.0, 0.0, 0.0, 0.0),
    (-0.08, 0.12, 0.0002, -0.0001, 0.0),
    (-0.2, 0.05, 0.001, -0.002, 0.01),
    (0.1, -0.05, 0.0005, 0.0003, 0.002, 0.05, -0.01, 0.003),
]


def camera(dist: tuple[float, ...]) -> CameraModel:
    return CameraModel(2909.1, 2905.0, 1020.0, 1030.0, 2048, 2048, dist)


def points(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    xy = rng.uniform(-0.35, 0.35, (n, 2))
    z = rng.uniform(600, 1500, n)
    return np.column_stack([xy * z[:, None], z])


@pytest.mark.parametrize("dist", DISTORTIONS)
def test_project_matches_opencv(dist: tuple[float, ...]) -> None:
    cam = camera(dist)
    p = points(np.random.default_rng(0))
    ref, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), cam.K, np.asarray(dist))
    assert np.max(np.abs(cam.project(p) - ref.reshape(-1, 2))) < 1e-8
    # the model's own numpy form (the Jacobian's pixels, distort_normalized) is the same model
    uv, _ = cam.project_with_jacobian(p)
    assert np.max(np.abs(uv - ref.reshape(-1, 2))) < 1e-8
    d = cam.distort_normalized(p[:, :2] / p[:, 2:3])
    assert np.max(np.abs(d * [cam.fx, cam.fy] + [cam.cx, cam.cy] - ref.reshape(-1, 2))) < 1e-8
    assert cam.project(np.empty((0, 3))).shape == (0, 2)


@pytest.mark.parametrize("dist", DISTORTIONS)
def test_jacobian_matches_finite_differences(dist: tuple[float, ...]) -> None:
    cam = camera(dist)
    p = points(np.random.default_rng(1), 30)
    uv, J = cam.project_with_jacobian(p)
    assert np.allclose(uv, cam.project(p))
    h = 1e-4
    for a in range(3):
        d = np.zeros(3)
        d[a] = h
        fd = (cam.project(p + d) - cam.project(p - d)) / (2 * h)
        assert np.allclose(J[:, :, a], fd, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("dist", DISTORTIONS[:3])
def test_undistort_inverts_projection(dist: tuple[float, ...]) -> None:
    cam = camera(dist)
    p = points(np.random.default_rng(2))
    xy = cam.undistort_normalized(cam.project(p))
    assert np.max(np.abs(xy - p[:, :2] / p[:, 2:3])) < 1e-9
    rays = cam.bearing(cam.project(p))
    assert np.allclose(rays, p / np.linalg.norm(p, axis=1, keepdims=True), atol=1e-9)
    ideal = cam.undistort_pixels(cam.project(p))
    assert np.allclose(ideal, camera((0.0, 0.0, 0.0, 0.0)).project(p), atol=1e-6)


def test_bad_camera_parameters_are_named() -> None:
    with pytest.raises(ValueError, match="fx"):
        CameraModel(-1.0, 1.0, 0.0, 0.0, 10, 10)
    with pytest.raises(ValueError, match="4, 5 or 8"):
        CameraModel(1.0, 1.0, 0.0, 0.0, 10, 10, (0.1, 0.2, 0.3))
    with pytest.raises(ValueError, match="image size"):
        CameraModel(1.0, 1.0, 0.0, 0.0, 0, 10)


def test_in_image_and_in_front() -> None:
    cam = camera(DISTORTIONS[0])
    inside = cam.in_image(np.array([[0.0, 0.0], [2047.4, 2047.4], [-1.0, 5.0], [5.0, 2048.0]]))
    assert inside.tolist() == [True, True, False, False]
    check_in_front(np.array([[0.0, 0.0, 1000.0]]), "ok")
    with pytest.raises(ValueError, match="mark M3: point 1 is behind the camera"):
        check_in_front(np.array([[0.0, 0.0, 1000.0], [0.0, 0.0, -5.0]]), "mark M3")
