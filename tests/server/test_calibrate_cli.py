"""``mvpose calibrate``: rendered board images and a robot-pose file through the real command."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from mvpose_core.calibration.boards import BoardSpec, render
from mvpose_core.calibration.files import load_calibration
from mvpose_core.calibration.synthetic import make_scene
from mvpose_core.camera import CameraModel
from mvpose_core.transforms import invert, to_robot, transform_error
from server.cli import main

CAM = CameraModel(900.0, 900.0, 402.0, 297.0, 800, 600, (-0.12, 0.08, 0.0003, -0.0002, 0.0))
BOARD = "chessboard:9x6:25"
LAB = Path(__file__).resolve().parents[2] / "deploy" / "stations" / "lab.yaml"


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory):
    """Eight rendered views from a robot-mounted camera, a KUKA pose CSV, and the truth."""
    root = tmp_path_factory.mktemp("calib")
    rng = np.random.default_rng(3)
    board = BoardSpec.parse(BOARD)
    scene = make_scene(
        rng, n_poses=8, stereo=False, board=board, camera=CAM, distance_mm=(330, 420)
    )
    folder = root / "images" / "left"
    folder.mkdir(parents=True)
    for sid in scene.robot_poses:
        img = render(board, CAM, scene.T_cf_from_bf("left", sid), rng)
        cv2.imwrite(str(folder / f"{sid}.png"), img)
    return root, scene


def _poses_csv(
    path: Path, scene, scale: float = 1.0, drop: str | None = None, inverted: bool = False
) -> Path:
    lines = ["id,X,Y,Z,A,B,C"]
    for sid, A in scene.robot_poses.items():
        if sid == drop:
            continue
        v = to_robot(invert(A) if inverted else A, "kuka")
        v[:3] *= scale
        lines.append(sid + "," + ",".join(f"{x:.5f}" for x in v))
    path.write_text("\n".join(lines) + "\n")
    return path


def _run(*argv: str | Path) -> int:
    return main(["calibrate", *[str(a) for a in argv]])


def test_handeye_from_images_and_pose_file(data, tmp_path: Path, capsys) -> None:
    root, scene = data
    poses = _poses_csv(tmp_path / "poses.csv", scene)
    out = tmp_path / "cal" / "handeye.json"
    code = _run(
        "handeye",
        "--images",
        root / "images",
        "--board",
        BOARD,
        "--poses",
        poses,
        "--convention",
        "kuka",
        "--out",
        out,
        "--no-progress",
    )
    assert code == 0, capsys.readouterr().err
    cal = load_calibration(out)  # verifies the content hash
    assert cal.kind == "handeye"
    assert cal.inputs.samples_used == sorted(scene.robot_poses)
    assert cal.inputs.robot_convention == "kuka" and len(cal.inputs.robot_poses_sha256) == 64
    X = cal.rigs["rig"].T_gf_from_rig.matrix  # no station: the rig frame is the camera frame
    deg, mm = transform_error(X, scene.X)
    assert mm < 0.5 and deg < 0.05, (deg, mm)
    fx = cal.cameras["left"].intrinsics.fx
    assert abs(fx / CAM.fx - 1) < 2e-3
    assert (out.with_suffix(".residuals.png")).read_bytes()[:4] == b"\x89PNG"
    text = out.with_suffix(".report.txt").read_text()
    assert "1σ T_gf_from_cf translation mm" in text and "leave-one-out" in text


def test_intrinsics_then_handeye_on_top(data, tmp_path: Path) -> None:
    root, scene = data
    base = tmp_path / "intr.json"
    assert (
        _run(
            "intrinsics",
            "--images",
            root / "images",
            "--board",
            BOARD,
            "--out",
            base,
            "--no-progress",
        )
        == 0
    )
    poses = _poses_csv(tmp_path / "poses.csv", scene)
    out = tmp_path / "he.json"
    assert (
        _run(
            "handeye",
            "--images",
            root / "images",
            "--board",
            BOARD,
            "--poses",
            poses,
            "--convention",
            "kuka",
            "--base",
            base,
            "--out",
            out,
            "--no-progress",
        )
        == 0
    )
    b, h = load_calibration(base), load_calibration(out)
    assert h.inputs.based_on == b.ref
    assert h.cameras["left"] == b.cameras["left"]  # intrinsics reused, not recalibrated


def test_missing_board_image_is_reported_and_left_out(data, tmp_path: Path) -> None:
    root, scene = data
    images = tmp_path / "images" / "left"
    images.mkdir(parents=True)
    for f in (root / "images" / "left").iterdir():
        data_bytes = f.read_bytes()
        if f.stem == "004":
            blank = np.full((CAM.height, CAM.width), 128, np.uint8)
            cv2.imwrite(str(images / f.name), blank)
        else:
            (images / f.name).write_bytes(data_bytes)
    poses = _poses_csv(tmp_path / "poses.csv", scene)
    out = tmp_path / "he.json"
    assert (
        _run(
            "handeye",
            "--images",
            tmp_path / "images",
            "--board",
            BOARD,
            "--poses",
            poses,
            "--convention",
            "kuka",
            "--out",
            out,
            "--no-progress",
        )
        == 0
    )
    cal = load_calibration(out)
    assert "004" not in cal.inputs.samples_used
    assert cal.inputs.samples_rejected["004"].startswith("left: board not found")
    assert transform_error(cal.rigs["rig"].T_gf_from_rig.matrix, scene.X)[1] < 0.5


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"scale": 0.001}, "wrong unit"),
        ({"drop": "005"}, r"images without a pose: \['005'\]"),
        # Exported as T_gf_from_rf: refused in one line naming the file, never a traceback.
        (
            {"inverted": True},
            r"poses.csv: hand-eye .*(do not fit the images|no solver gave a plau)",
        ),
    ],
)
def test_bad_pose_files_name_the_problem(data, tmp_path: Path, capsys, kwargs, message) -> None:
    root, scene = data
    poses = _poses_csv(tmp_path / "poses.csv", scene, **kwargs)
    code = _run(
        "handeye",
        "--images",
        root / "images",
        "--board",
        BOARD,
        "--poses",
        poses,
        "--convention",
        "kuka",
        "--out",
        tmp_path / "x.json",
        "--no-progress",
    )
    assert code == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "x.json").exists()


def test_bad_board_and_wrong_header(data, tmp_path: Path, capsys) -> None:
    root, scene = data
    assert (
        _run(
            "intrinsics",
            "--images",
            root / "images",
            "--board",
            "chess:9x6",
            "--out",
            tmp_path / "x.json",
        )
        == 2
    )
    assert "--board" in capsys.readouterr().err
    poses = _poses_csv(tmp_path / "poses.csv", scene)
    assert (
        _run(
            "handeye",
            "--images",
            root / "images",
            "--board",
            BOARD,
            "--poses",
            poses,
            "--convention",
            "fanuc",
            "--out",
            tmp_path / "x.json",
            "--no-progress",
        )
        == 2
    )
    assert "does not match the fanuc convention" in capsys.readouterr().err


def _render_all(root: Path, scene_cams: dict, poses: dict, board: BoardSpec, rng) -> None:
    """Write IMAGES/<camera>/<sample>.png for T_cf_from_bf given per (camera, sample)."""
    for cid, cam in scene_cams.items():
        (root / cid).mkdir(parents=True, exist_ok=True)
        for sid in poses:
            cv2.imwrite(str(root / cid / f"{sid}.png"), render(board, cam, poses[sid](cid), rng))


def test_stereo_from_images(tmp_path: Path) -> None:
    rng = np.random.default_rng(8)
    board = BoardSpec.parse(BOARD)
    scene = make_scene(
        rng,
        n_poses=8,
        board=board,
        camera=CAM,
        distance_mm=(380, 450),
        baseline_mm=100.0,
        converge_mm=420.0,
    )
    poses = {sid: (lambda cid, sid=sid: scene.T_cf_from_bf(cid, sid)) for sid in scene.robot_poses}
    _render_all(tmp_path / "images", scene.cameras, poses, board, rng)
    out = tmp_path / "stereo.json"
    assert (
        _run(
            "stereo",
            "--images",
            tmp_path / "images",
            "--board",
            BOARD,
            "--out",
            out,
            "--no-progress",
        )
        == 0
    )
    cal = load_calibration(out)
    rig = cal.rigs["rig"]
    T_rig_from_right = rig.T_rig_from_cf["right"].matrix  # rig frame = left camera
    T_right_from_left = np.linalg.inv(T_rig_from_right)
    assert abs(np.linalg.norm(T_right_from_left[:3, 3]) - 100.0) < 0.1
    deg, mm = transform_error(T_right_from_left, scene.T_cfc_from_cf0["right"])
    assert mm < 0.5 and deg < 0.05


def _station_yaml(path: Path, scene) -> Path:
    """A two-camera fixed station with nominal (uncalibrated) poses 20 mm / 1° off."""
    import yaml

    from mvpose_core.calibration.files import pose

    cams, rigs = [], []
    for cid, T in scene.T_rf_from_cf.items():
        cams.append(
            {
                "id": cid,
                "driver": {"kind": "sim"},
                "image_size": [CAM.width, CAM.height],
                "intrinsics": {"fx": 890.0, "fy": 890.0, "cx": 400.0, "cy": 300.0},
            }
        )
        nominal = pose(T).model_dump(mode="json")
        nominal["xyz"][0] += 20.0
        nominal["wpr"][2] += 1.0
        rigs.append(
            {
                "id": f"rig_{cid}",
                "mount": "fixed",
                "cameras": [{"camera": cid}],
                "T_rf_from_rig": nominal,
            }
        )
    data = {
        "name": "bench",
        "cameras": cams,
        "rigs": rigs,
        "views": [{"id": 1, "rigs": [r["id"] for r in rigs]}],
        "recipes": [
            {
                "name": "plate",
                "mark_diameter_mm": 10.0,
                "marks": [{"id": f"m{k}", "position": [100.0 * k, 0.0, 0.0]} for k in range(3)],
                "sightings": [{"view": 1, "camera": "cam1", "marks": ["m0", "m1", "m2"]}],
                "T_rf_from_pf0": {"xyz": [1500.0, 200.0, 0.0]},
            }
        ],
    }
    path.write_text(yaml.safe_dump(data))
    return path


def test_station_from_images_applies_to_the_station_file(tmp_path: Path) -> None:
    from mvpose_core.calibration.files import apply_calibration
    from mvpose_core.calibration.synthetic import make_station_scene
    from mvpose_core.scene import view_cameras
    from mvpose_core.station import load_station
    from mvpose_core.transforms import compose, invert

    rng = np.random.default_rng(4)
    board = BoardSpec.parse(BOARD)
    scene = make_station_scene(
        rng, n_placements=8, n_cameras=2, spacing_mm=150.0, height_mm=550.0, board=board, camera=CAM
    )
    poses = {
        sid: (lambda cid, T=T: compose(invert(scene.T_rf_from_cf[cid]), T))
        for sid, T in scene.T_rf_from_bf.items()
    }
    _render_all(tmp_path / "images", scene.cameras, poses, board, rng)
    lines = ["id,X,Y,Z,W,P,R"] + [
        sid + "," + ",".join(f"{v:.5f}" for v in to_robot(T, "fanuc"))
        for sid, T in scene.T_rf_from_bf.items()
    ]
    (tmp_path / "board_poses.csv").write_text("\n".join(lines) + "\n")
    station_file = _station_yaml(tmp_path / "station.yaml", scene)
    out = tmp_path / "station.json"
    assert (
        _run(
            "station",
            "--images",
            tmp_path / "images",
            "--board",
            BOARD,
            "--station",
            station_file,
            "--board-poses",
            tmp_path / "board_poses.csv",
            "--convention",
            "fanuc",
            "--out",
            out,
            "--no-progress",
        )
        == 0
    )
    calibrated = apply_calibration(load_station(station_file), load_calibration(out))
    for vc in view_cameras(calibrated):
        deg, mm = transform_error(vc.T_rf_from_cf, scene.T_rf_from_cf[vc.camera_id])
        assert mm < 0.5 and deg < 0.05, (vc.camera_id, deg, mm)
        assert abs(vc.model.fx / CAM.fx - 1) < 3e-3


def test_synthetic_set_rehearses_the_handeye_step(tmp_path: Path, capsys) -> None:
    """`calibrate synthetic` renders the lab station's stereo rig (at a quarter of its size) with
    robot poses carrying a good robot's error; `calibrate handeye` on it finds the true hand-eye
    within the reported 1σ's reach, and its report shows the values the file holds."""
    import json

    root = tmp_path / "syn"
    board = "charuco:10x8:40:30"
    code = _run(
        "synthetic", "--station", LAB, "--out", root, "--board", board, "--samples", "10",
        "--distance", "1000", "--robot-error", "0.05", "0.01", "--image-scale", "0.25",
        "--seed", "1", "--no-progress",
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    truth = json.loads((root / "truth.json").read_text())
    assert truth["robot_error_per_axis"] == {"mm": 0.05, "deg": 0.01}
    assert sorted(p.name for p in (root / "images").iterdir()) == ["left", "right"]
    assert len(list((root / "images" / "right").glob("*.png"))) == 10
    assert (root / "poses.csv").read_text().startswith("id,X,Y,Z,W,P,R\n")  # lab: fanuc
    out = tmp_path / "he.json"
    code = _run(
        "handeye", "--images", root / "images", "--board", board, "--poses", root / "poses.csv",
        "--convention", "fanuc", "--out", out, "--no-progress",
    )  # fmt: skip
    assert code == 0, capsys.readouterr().err
    cal = load_calibration(out)
    X = cal.rigs["rig"].T_gf_from_rig.matrix  # no station: the rig frame is the left camera's
    deg, mm = transform_error(X, np.array(truth["T_gf_from_cf"]["left"]))
    sigma = cal.report["handeye (robot)"]["sigma"]
    reach = 3 * max(
        sigma["T_gf_from_cf translation mm"], sigma["T_gf_from_cf translation mm (jackknife)"]
    )
    assert mm < reach, (mm, sigma)
    text = out.with_suffix(".report.txt").read_text()
    fx = cal.cameras["left"].intrinsics.fx
    held = cal.report["handeye (robot)"]["result"]["left fx px"]
    assert abs(held - fx) < 0.01 and f"left fx px: {held!r}" in text
