"""Boards: rendered images with known truth go through OpenCV detection back to the true corners."""

from __future__ import annotations

import numpy as np
import pytest

from mvpose_core.calibration.boards import BoardSpec, detect, render
from mvpose_core.calibration.intrinsics import calibrate_intrinsics
from mvpose_core.calibration.synthetic import make_scene
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import apply, make_transform, zyx_to_matrix

CAM = CameraModel(900.0, 900.0, 402.0, 297.0, 800, 600, (-0.12, 0.08, 0.0003, -0.0002, 0.0))


def _pose(board: BoardSpec, angles: tuple[float, float, float], dist: float) -> np.ndarray:
    R = zyx_to_matrix(*angles)
    c = board.object_points.mean(axis=0)
    return make_transform(R, np.array([10.0, -5.0, dist]) - R @ c)


@pytest.mark.parametrize(
    ("spec", "rms_px"),
    [("chessboard:9x6:25", 0.1), ("charuco:7x5:30:22", 0.15), ("circles:4x11:15:8", 0.06)],
)
@pytest.mark.parametrize("angles", [(10.0, 20.0, 15.0), (180.0, -15.0, 10.0), (-90.0, 5.0, -25.0)])
def test_rendered_board_is_detected_at_the_true_corners(spec: str, rms_px: float, angles) -> None:
    board = BoardSpec.parse(spec)
    T = _pose(board, angles, 480.0 if board.kind != "circles" else 400.0)
    img = render(board, CAM, T, np.random.default_rng(7))
    d = detect(img, board)
    assert d is not None
    assert len(d) >= (board.n_corners if board.kind != "charuco" else 12)
    truth = CAM.project(apply(T, board.object_points[d.ids]))
    err = np.linalg.norm(d.uv - truth, axis=1)
    # Rotated by 180° or 90° must not come back reordered (that would be errors of a square,
    # tens of px): every corner keeps its id, to the renderer's and detector's accuracy.
    assert err.max() < 0.4, err.max()
    assert np.sqrt(np.mean(err**2)) < rms_px


def test_board_not_in_image_is_not_found() -> None:
    board = BoardSpec.parse("chessboard:9x6:25")
    T = make_transform(np.eye(3), [2000.0, 0.0, 500.0])
    assert detect(render(board, CAM, T, np.random.default_rng(1)), board) is None


def test_board_spec_text_round_trip_and_errors() -> None:
    for text in ("chessboard:9x6:25", "charuco:7x5:30:22:DICT_5X5_100", "circles:4x11:20:10"):
        assert str(BoardSpec.parse(text)) == text
    with pytest.raises(ValueError, match="180°-symmetric"):
        BoardSpec.parse("chessboard:8x6:25")
    with pytest.raises(ValueError, match="not understood"):
        BoardSpec.parse("chess 9x6")
    with pytest.raises(ValueError, match="marker_mm"):
        BoardSpec.parse("charuco:7x5:30:40")


def test_full_path_rendered_images_to_intrinsics() -> None:
    """Render, detect with OpenCV and calibrate: the whole path, no synthetic detections."""
    rng = np.random.default_rng(11)
    board = BoardSpec.parse("chessboard:9x6:25")
    scene = make_scene(
        rng,
        n_poses=10,
        stereo=False,
        board=board,
        camera=CAM,
        distance_mm=(330.0, 420.0),
        max_tilt_deg=35.0,
    )
    dets = {
        sid: detect(render(board, CAM, scene.T_cf_from_bf("left", sid), rng), board)
        for sid in scene.robot_poses
    }
    res = calibrate_intrinsics("left", dets, board, (CAM.width, CAM.height))
    assert not res.rejected
    assert abs(res.camera.fx / CAM.fx - 1) < 2e-3
    assert abs(res.camera.cx - CAM.cx) < 1.5
    assert res.rms_px < 0.2
