"""``mvpose calibrate synthetic``: a rendered board image set for a station file with the robot
poses (robot-mounted rig) or the board poses in RF (fixed cameras) and the truth, to rehearse
the calibration steps on a laptop; ``mvpose calibrate compare``: a calibration file against that
truth.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

import numpy as np

from server.cli import CliError


def add_parsers(sub: Any) -> None:
    _add_synthetic(sub)
    text = "compare a calibration file with the truth of a synthetic set (a rehearsal's check)"
    p = sub.add_parser("compare", help=text, description=text)
    p.add_argument("calibration", type=Path, help="calibration file (.json) to check")
    p.add_argument(
        "--truth", type=Path, required=True, help="truth.json of `mvpose calibrate synthetic`"
    )


def _add_synthetic(sub: Any) -> None:
    text = (
        "render board images of a station's robot-mounted rig with the robot poses (exact or "
        "with a chosen robot error) and the true hand-eye; for a station with fixed cameras "
        "only, board placements seen by two or more cameras with their poses in RF"
    )
    p = sub.add_parser("synthetic", help=text, description=text)
    p.add_argument("--station", type=Path, required=True, help="station YAML (cameras, rig)")
    p.add_argument("--out", type=Path, required=True, help="folder to write (images, poses)")
    p.add_argument("--board", default="charuco:15x11:40:30", help="board (default %(default)s)")
    p.add_argument("--rig", help="robot-mounted rig (default: the station's first)")
    p.add_argument(
        "--samples",
        type=int,
        default=18,
        help="robot poses, or board placements of a fixed station (default 18)",
    )
    p.add_argument(
        "--distance", type=float, default=1700.0, help="camera–board distance mm (±10 %%)"
    )
    p.add_argument(
        "--robot-error",
        nargs=2,
        type=float,
        default=(0.0, 0.0),
        metavar=("MM", "DEG"),
        help="1σ per axis of the written flange poses (default exact: 0 0)",
    )
    p.add_argument("--convention", help="robot convention of poses.csv (default: the recipe's)")
    p.add_argument(
        "--image-scale",
        type=float,
        default=1.0,
        help="render at this fraction of the station's image size (e.g. 0.25 for a quick run)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _step_synthetic(args: argparse.Namespace) -> int:
    import json

    import cv2
    from tqdm import tqdm

    from mvpose_core.calibration.boards import BoardSpec, render
    from mvpose_core.calibration.synthetic import (
        CalibScene,
        board_in_front,
        view_poses,
        with_robot_error,
    )
    from mvpose_core.station import load_station
    from mvpose_core.transforms import RobotConvention, invert, to_robot

    try:
        board = BoardSpec.parse(args.board)
    except ValueError as err:
        raise CliError(f"--board: {err}") from None
    station = load_station(args.station)
    if not (args.samples >= 3 and args.distance > 0 and 0 < args.image_scale <= 1):
        raise CliError("--samples ≥ 3, --distance > 0 and 0 < --image-scale ≤ 1, please")
    mm, deg = args.robot_error
    if not (mm >= 0 and deg >= 0):
        raise CliError(f"--robot-error: both values must be ≥ 0, got {mm:g} {deg:g}")
    rigs = [r for r in station.rigs if args.rig in (None, r.id)]
    if not rigs:
        raise CliError(f"station {station.name!r} has no rig {args.rig!r}")
    if not any(r.mount == "robot" for r in rigs):
        return _synthetic_station(args, station, board, [r for r in rigs if r.mount == "fixed"])
    rig = next(r for r in rigs if r.mount == "robot")
    k = args.image_scale
    cameras = {rc.camera: _scaled(station.camera(rc.camera), k) for rc in rig.cameras}
    T_rig_from = {rc.camera: rc.T_rig_from_cf.matrix for rc in rig.cameras}
    ref = rig.cameras[0].camera
    assert rig.T_gf_from_rig is not None  # a robot-mounted rig has one (station model)
    X = rig.T_gf_from_rig.matrix @ T_rig_from[ref]
    rel = {c: invert(T_rig_from[c]) @ T_rig_from[ref] for c in cameras}
    Y = board_in_front()
    rng = np.random.default_rng(args.seed)
    d = args.distance
    try:
        poses = view_poses(
            rng, "robot", board, cameras, rel, X, Y, args.samples, (0.9 * d, 1.1 * d), 30.0
        )
    except ValueError as err:
        raise CliError(f"synthetic: {err}; try another --distance or a smaller --board") from None
    scene = CalibScene("robot", board, cameras, rel, X, Y, poses)
    written = with_robot_error(rng, poses, mm, deg) if mm > 0 or deg > 0 else poses
    conv = RobotConvention(args.convention or station.recipe().robot_convention)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows = [",".join(["id", *conv.labels])]
    for sid, A in written.items():
        rows.append(sid + "," + ",".join(f"{v:.6f}" for v in to_robot(A, conv)))
    (out / "poses.csv").write_text("\n".join(rows) + "\n")
    truth = {
        "station": station.name,
        "rig": rig.id,
        "board": str(board),
        "convention": conv.value,
        "robot_error_per_axis": {"mm": mm, "deg": deg},
        "seed": args.seed,
        "image_scale": k,
        "T_gf_from_rig": rig.T_gf_from_rig.matrix.tolist(),
        "T_gf_from_cf": {c: (X @ invert(rel[c])).tolist() for c in cameras},
        "T_rf_from_bf": Y.tolist(),
        "T_rf_from_gf_exact": {sid: A.tolist() for sid, A in poses.items()},
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    with tqdm(
        total=len(poses) * len(cameras), desc="render", unit="img", file=sys.stderr,
        disable=args.no_progress,
    ) as bar:  # fmt: skip
        for cid, cam in cameras.items():
            (out / "images" / cid).mkdir(parents=True, exist_ok=True)
            for sid in poses:
                img = render(board, cam, scene.T_cf_from_bf(cid, sid), rng)
                cv2.imwrite(str(out / "images" / cid / f"{sid}.png"), img)
                bar.update(1)
    print(
        f"wrote {len(poses)} samples × {len(cameras)} cameras to {out / 'images'}, robot poses "
        f"({conv.value}, error {mm:g} mm / {deg:g}° per axis) to {out / 'poses.csv'}, the truth "
        f"to {out / 'truth.json'}"
    )
    return 0


def _step_compare(args: argparse.Namespace) -> int:
    """Each camera's hand-eye (or, in a stereo file, its pose relative to the first camera)
    against ``truth.json``, beside the 1σ the file's report gives."""
    import json

    from mvpose_core.calibration.files import load_calibration

    calib = load_calibration(args.calibration)
    try:
        truth = json.loads(args.truth.read_text())
        if "T_rf_from_cf" in truth:
            return _compare_station(calib, truth)
        lines = rig_against_truth(calib, truth)
    except (OSError, ValueError, KeyError, TypeError, StopIteration) as err:
        raise CliError(f"{args.truth}: not the truth of this calibration's rig ({err!r})") from None
    except LookupError as err:
        raise CliError(f"{args.calibration}: {err.args[0]}") from None
    print("\n".join(lines))
    return 0


def rig_against_truth(calib: Any, truth: dict[str, Any]) -> list[str]:
    """The lines of ``calibrate compare`` for a robot-mounted rig's set: each camera's
    T_gf_from_cf (a stereo file: its pose in the first camera's) against the truth, and the 1σ
    the calibration reports. KeyError or TypeError: not such a truth; LookupError with a
    message: the calibration holds none of its cameras."""
    from mvpose_core.transforms import invert, transform_error

    T_true = {c: np.array(T) for c, T in truth["T_gf_from_cf"].items()}
    # Without --station the calibration names its rig "rig"; one rig is the one meant.
    rigs = calib.rigs
    rig = rigs[truth["rig"]] if truth["rig"] in rigs else next(iter(rigs.values()))
    sigma: dict[str, float] = {}
    for rep in calib.report.values():
        sigma.update(rep.get("sigma", {}))
    cams = [c for c in T_true if c in rig.T_rig_from_cf]
    if not cams:
        raise LookupError(f"rig {truth['rig']!r} holds none of {list(T_true)}")
    lines = []
    if rig.T_gf_from_rig is not None:
        X = rig.T_gf_from_rig.matrix
        for c in cams:
            deg, mm = transform_error(X @ rig.T_rig_from_cf[c].matrix, T_true[c])
            lines.append(f"{c}: T_gf_from_cf is {mm:.3f} mm / {deg:.4f}° from the truth")
        key = "T_gf_from_cf"
    else:
        ref = cams[0]
        for c in cams[1:]:
            est = invert(rig.T_rig_from_cf[ref].matrix) @ rig.T_rig_from_cf[c].matrix
            deg, mm = transform_error(est, invert(T_true[ref]) @ T_true[c])
            lines.append(
                f"{c}: its pose in {ref}'s frame is {mm:.3f} mm / {deg:.4f}° from the truth"
            )
        key = "T_cf1_from_cf2"
    mm_s, deg_s = sigma.get(f"{key} translation mm"), sigma.get(f"{key} rotation deg")
    if mm_s is not None and deg_s is not None:
        lines.append(f"reported 1σ ({key}): {mm_s:g} mm / {deg_s:g}°")
    return lines


def _scaled(c: Any, k: float) -> Any:
    """The station camera's model rendered at ``k`` times its image size."""
    from mvpose_core.camera import CameraModel

    i = c.intrinsics
    w, h = c.image_size
    return CameraModel(
        i.fx * k, i.fy * k, (i.cx + 0.5) * k - 0.5, (i.cy + 0.5) * k - 0.5,
        round(w * k), round(h * k), tuple(c.distortion),
    )  # fmt: skip


def _synthetic_station(args: argparse.Namespace, station: Any, board: Any, rigs: list) -> int:
    """A fixed station's set: board placements seen by two or more cameras at once, their
    poses in RF as measured (``board_poses.csv``, off by ``--robot-error``), and the truth."""
    import json

    import cv2
    from tqdm import tqdm

    from mvpose_core.calibration.boards import render
    from mvpose_core.calibration.synthetic import station_placements, with_robot_error
    from mvpose_core.transforms import RobotConvention, invert, to_robot

    if not rigs:
        raise CliError(f"station {station.name!r} has no fixed or robot-mounted rig")
    k = args.image_scale
    cameras, T_rf_from_cf = {}, {}
    for rig in rigs:
        for rc in rig.cameras:
            cameras[rc.camera] = _scaled(station.camera(rc.camera), k)
            T_rf_from_cf[rc.camera] = rig.T_rf_from_rig.matrix @ rc.T_rig_from_cf.matrix
    rng = np.random.default_rng(args.seed)
    try:
        poses = station_placements(rng, board, cameras, T_rf_from_cf, args.samples)
    except ValueError as err:
        raise CliError(f"synthetic: {err}") from None
    mm, deg = args.robot_error
    written = with_robot_error(rng, poses, mm, deg) if mm > 0 or deg > 0 else poses
    conv = RobotConvention(args.convention or station.recipe().robot_convention)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows = [",".join(["id", *conv.labels])]
    for sid, T in written.items():
        rows.append(sid + "," + ",".join(f"{v:.6f}" for v in to_robot(T, conv)))
    (out / "board_poses.csv").write_text("\n".join(rows) + "\n")
    truth = {
        "station": station.name,
        "rigs": [r.id for r in rigs],
        "board": str(board),
        "convention": conv.value,
        "board_pose_error_per_axis": {"mm": mm, "deg": deg},
        "seed": args.seed,
        "image_scale": k,
        "T_rf_from_cf": {c: T.tolist() for c, T in T_rf_from_cf.items()},
        "T_rf_from_bf_exact": {sid: T.tolist() for sid, T in poses.items()},
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1) + "\n")
    _scaled_station_file(args.station, out / "station.yaml", k)
    with tqdm(
        total=len(poses) * len(cameras), desc="render", unit="img", file=sys.stderr,
        disable=args.no_progress,
    ) as bar:  # fmt: skip
        for cid, cam in cameras.items():
            (out / "images" / cid).mkdir(parents=True, exist_ok=True)
            for sid, T in poses.items():
                img = render(board, cam, invert(T_rf_from_cf[cid]) @ T, rng)
                cv2.imwrite(str(out / "images" / cid / f"{sid}.png"), img)
                bar.update(1)
    print(
        f"wrote {len(poses)} board placements × {len(cameras)} fixed cameras to "
        f"{out / 'images'}, the board poses in RF ({conv.value}, error {mm:g} mm / {deg:g}° per "
        f"axis) to {out / 'board_poses.csv'}, the truth to {out / 'truth.json'}, the station "
        f"at this image size to {out / 'station.yaml'}"
    )
    return 0


def _scaled_station_file(src: Path, dst: Path, k: float) -> None:
    """The station file with every camera's image size and intrinsics at ``k`` times (what the
    calibration steps check the rendered images against); the rest as written."""
    import yaml

    data = yaml.safe_load(src.read_text())
    scale_cameras(data, k)
    dst.write_text(
        f"# {src.name} with its cameras at {k:g} × their image size (mvpose calibrate "
        "synthetic)\n" + yaml.safe_dump(data, sort_keys=False)
    )


def scale_cameras(data: dict[str, Any], k: float) -> None:
    """A station file's data (as YAML loads it) with every camera's image size and intrinsics at
    ``k`` times: the cameras a set rendered at ``--image-scale k`` was seen with."""
    for cam in data["cameras"]:
        # New dicts: YAML anchors share one intrinsics mapping between cameras.
        i = cam["intrinsics"]
        cam["intrinsics"] = {
            **i,
            "fx": i["fx"] * k,
            "fy": i["fy"] * k,
            "cx": (i["cx"] + 0.5) * k - 0.5,
            "cy": (i["cy"] + 0.5) * k - 0.5,
        }
        cam["image_size"] = [round(v * k) for v in cam["image_size"]]


def _compare_station(calib: Any, truth: dict[str, Any]) -> int:
    from mvpose_core.transforms import invert, transform_error

    T_true = {c: np.array(T) for c, T in truth["T_rf_from_cf"].items()}
    est: dict[str, np.ndarray] = {}
    for rig in calib.rigs.values():
        if rig.T_rf_from_rig is not None:
            for c, T in rig.T_rig_from_cf.items():
                est[c] = rig.T_rf_from_rig.matrix @ T.matrix
    cams = [c for c in T_true if c in est]
    if not cams:
        raise CliError(f"the calibration places none of the cameras {list(T_true)} in RF")
    sigma: dict[str, float] = {}
    for rep in calib.report.values():
        sigma.update(rep.get("sigma", {}))
    ref = cams[0]
    for c in cams:
        deg, mm = transform_error(est[c], T_true[c])
        line = f"{c}: T_rf_from_cf is {mm:.3f} mm / {deg:.4f}° from the truth"
        if f"{c} in RF translation mm" in sigma:
            line += f" (1σ {sigma[f'{c} in RF translation mm']:g} mm / "
            line += f"{sigma[f'{c} in RF rotation deg']:g}°)"
        if c != ref:
            deg, mm = transform_error(invert(est[ref]) @ est[c], invert(T_true[ref]) @ T_true[c])
            line += f"; from {ref}: {mm:.3f} mm / {deg:.4f}°"
            keys = [k for k in sigma if k.startswith(f"{c} from ") and k.endswith(" mm")]
            if keys and keys[0] == f"{c} from {ref} translation mm":
                line += f" (1σ {sigma[keys[0]]:g} mm / {sigma[f'{c} from {ref} rotation deg']:g}°)"
        print(line)
    return 0


STEPS = {"synthetic": _step_synthetic, "compare": _step_compare}
