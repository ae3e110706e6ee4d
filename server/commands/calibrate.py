"""``mvpose calibrate intrinsics|stereo|handeye|station``: board images (+ robot poses) to a
versioned calibration file, a text report and a residual plot. ``mvpose calibrate synthetic``
and ``compare`` (rehearsing the steps on a laptop) live in :mod:`server.commands.rehearsal`,
``rehearse-handeye`` and ``rehearse-verify`` (through the PLC twin) in
:mod:`server.commands.rehearse_robot`.

Images live in ``IMAGES/<camera id>/<sample id>.<png|bmp|tif|jpg>``; the file stem is the sample
id that pairs an image with its robot pose (never the position in a list).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from server.cli import CliError
from server.commands import rehearsal, rehearse_robot

_EXTS = (".png", ".bmp", ".tif", ".tiff", ".jpg", ".jpeg")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="step", metavar="STEP", required=True)
    helps = {
        "intrinsics": "camera matrix and distortion of each camera",
        "stereo": "intrinsics of two cameras and their relative pose",
        "handeye": "cameras on the robot: intrinsics, stereo and T_gf_from_rig",
        "station": "fixed cameras: relations from images, then one rigid placement in RF",
    }
    rehearsal.add_parsers(sub)
    rehearse_robot.add_parsers(sub)
    for name, text in helps.items():
        p = sub.add_parser(name, help=text, description=text)
        p.add_argument(
            "--images", type=Path, required=True, help="folder IMAGES/<camera>/<sample>.png"
        )
        p.add_argument("--board", required=True, help="e.g. chessboard:9x6:25 or charuco:7x5:30:22")
        p.add_argument("--cameras", nargs="+", help="camera ids (default: every sub-folder)")
        p.add_argument("--station", type=Path, help="station YAML (camera ids, rigs, image sizes)")
        p.add_argument("--base", type=Path, help="earlier calibration file to start from")
        p.add_argument("--out", type=Path, required=True, help="calibration file to write (.json)")
        p.add_argument(
            "--distortion",
            type=int,
            choices=[4, 5, 8],
            default=5,
            help="distortion terms for intrinsics (default 5)",
        )
        p.add_argument("--no-progress", action="store_true", help="no progress bar")
        p.add_argument("--rig", help="rig id (default: the station rig holding the cameras)")
        if name in ("handeye", "station"):
            p.add_argument("--poses", type=Path, help="robot flange poses per sample (CSV or JSON)")
            p.add_argument(
                "--convention",
                help="robot convention of the pose files (fanuc, yaskawa, kuka, abb, ur)",
            )
        if name == "handeye":
            p.add_argument(
                "--fix-intrinsics",
                action="store_true",
                help="hold the intrinsics in the bundle adjustment (always so with --base)",
            )
            p.add_argument(
                "--robot-sigma",
                nargs=2,
                type=float,
                metavar=("MM", "DEG"),
                help="the robot's pose accuracy per axis (1σ): position mm, rotation deg "
                "(default: the station's uncertainty.robot_repeatability, else 0.05 0.01)",
            )
            p.add_argument(
                "--board-pose",
                type=Path,
                help="board pose in RF (paper eq. 10): a one-row pose file, id 'board'",
            )
        if name == "station":
            p.add_argument(
                "--board-poses",
                type=Path,
                help="board pose in RF per sample (measured), instead of --poses",
            )


def run(args: argparse.Namespace) -> int:
    from mvpose_core.calibration.errors import CalibrationError
    from mvpose_core.calibration.files import CalibrationFileError
    from mvpose_core.station import StationFileError

    try:
        return _STEPS[args.step](args)
    except (CalibrationError, CalibrationFileError, StationFileError) as err:
        raise CliError(str(err)) from None


# --------------------------------------------------------------------------- inputs


def _image_files(args: argparse.Namespace) -> dict[str, dict[str, Path]]:
    root: Path = args.images
    if not root.is_dir():
        raise CliError(f"--images {root}: not a folder")
    folders = sorted(p for p in root.iterdir() if p.is_dir())
    wanted = args.cameras or [p.name for p in folders]
    if not wanted:
        raise CliError(
            f"--images {root}: no camera sub-folders (expected {root}/<camera>/<sample>.png)"
        )
    out: dict[str, dict[str, Path]] = {}
    for cid in wanted:
        folder = root / cid
        files = (
            sorted(f for f in folder.glob("*") if f.suffix.lower() in _EXTS)
            if folder.is_dir()
            else []
        )
        if not files:
            raise CliError(f"--images {root}: no images for camera {cid!r} in {folder}")
        out[cid] = {f.stem: f for f in files}
    return out


def _detect_all(
    args: argparse.Namespace, board: Any, files: dict[str, dict[str, Path]]
) -> tuple[dict[str, dict[str, Any]], dict[str, tuple[int, int]]]:
    import cv2
    from tqdm import tqdm

    from mvpose_core.calibration.boards import detect

    dets: dict[str, dict[str, Any]] = {}
    sizes: dict[str, tuple[int, int]] = {}
    total = sum(len(v) for v in files.values())
    with tqdm(
        total=total, desc="detect board", unit="img", file=sys.stderr, disable=args.no_progress
    ) as bar:
        for cid, per in files.items():
            dets[cid] = {}
            for sid, path in per.items():
                img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
                if img is None:
                    raise CliError(f"{path}: cannot read image")
                size = (img.shape[1], img.shape[0])
                if sizes.setdefault(cid, size) != size:
                    raise CliError(
                        f"{path}: image is {size[0]}x{size[1]}, camera {cid!r} others are "
                        f"{sizes[cid][0]}x{sizes[cid][1]}"
                    )
                dets[cid][sid] = detect(np.asarray(img, dtype=np.uint8), board)
                bar.update(1)
    return dets, sizes


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _common(args: argparse.Namespace) -> dict[str, Any]:
    from mvpose_core.calibration.boards import BoardSpec
    from mvpose_core.calibration.files import load_calibration
    from mvpose_core.station import load_station

    try:
        board = BoardSpec.parse(args.board)
    except ValueError as err:
        raise CliError(f"--board: {err}") from None
    station = load_station(args.station) if args.station else None
    base = load_calibration(args.base) if args.base else None
    files = _image_files(args)
    if station is not None:
        known = {c.id for c in station.cameras}
        unknown = sorted(set(files) - known)
        if unknown:
            raise CliError(f"cameras {unknown} (image folders) are not in station {station.name!r}")
    dets, sizes = _detect_all(args, board, files)
    for cid in dets:
        if station is not None and tuple(station.camera(cid).image_size) != sizes[cid]:
            want = station.camera(cid).image_size
            raise CliError(
                f"camera {cid!r}: images are {sizes[cid][0]}x{sizes[cid][1]}, "
                f"station says {want[0]}x{want[1]}"
            )
    return {"board": board, "station": station, "base": base, "dets": dets, "sizes": sizes}


def _intrinsics(ctx: dict[str, Any], args: argparse.Namespace, reports: list) -> dict[str, Any]:
    """Camera models: from --base when it has them, else calibrated from these images."""
    from mvpose_core.calibration.intrinsics import IntrinsicsOptions, calibrate_intrinsics
    from mvpose_core.calibration.report import intrinsics_report
    from mvpose_core.camera import CameraModel

    models: dict[str, CameraModel] = {}
    base = ctx["base"]
    opt = IntrinsicsOptions(n_distortion=args.distortion)
    for cid, dets in ctx["dets"].items():
        if base is not None and cid in base.cameras and args.step != "intrinsics":
            c = base.cameras[cid]
            i = c.intrinsics
            w, h = c.image_size
            models[cid] = CameraModel(i.fx, i.fy, i.cx, i.cy, w, h, tuple(c.distortion))
            continue
        res = calibrate_intrinsics(cid, dets, ctx["board"], ctx["sizes"][cid], opt)

        def solve(ids: list[str], cid: str = cid, dets: dict = dets) -> Any:
            return calibrate_intrinsics(
                cid, {i: dets[i] for i in ids}, ctx["board"], ctx["sizes"][cid], opt
            )

        reports.append((intrinsics_report(res, solve), None))
        models[cid] = res.camera
    return models


# --------------------------------------------------------------------------- steps


def _step_intrinsics(args: argparse.Namespace) -> int:
    ctx = _common(args)
    reports: list = []
    models = _intrinsics(ctx, args, reports)
    return _write(args, ctx, "intrinsics", models, {}, reports)


def _step_stereo(args: argparse.Namespace) -> int:
    from mvpose_core.calibration.report import stereo_report
    from mvpose_core.calibration.stereo import calibrate_stereo
    from mvpose_core.transforms import invert

    ctx = _common(args)
    if len(ctx["dets"]) != 2:
        raise CliError(f"stereo needs exactly two cameras, got {list(ctx['dets'])}")
    reports: list = []
    models = _intrinsics(ctx, args, reports)
    c1, c2 = list(ctx["dets"])
    d1, d2 = ctx["dets"][c1], ctx["dets"][c2]
    res = calibrate_stereo(c1, c2, d1, d2, ctx["board"], models[c1], models[c2])

    def solve(ids: list[str]) -> Any:
        # Repeatability of the relative pose alone (intrinsics held): the joint solve is slow.
        sub1, sub2 = {i: d1[i] for i in ids}, {i: d2[i] for i in ids}
        return calibrate_stereo(
            c1, c2, sub1, sub2, ctx["board"], res.model1, res.model2, refine_intrinsics=False
        )

    depth = float(np.median([T[2, 3] for T in _board_depths(ctx, models, c1)]))
    reports = _as_start(reports, "stereo")
    reports.append((stereo_report(res, depth, solve), None))
    models = {c1: res.model1, c2: res.model2}
    rig_id, T_rig_from_cf1 = _rig_frame(ctx, args, c1, "robot", allow_any=True)
    rig = _rig(None, None, {c1: T_rig_from_cf1, c2: T_rig_from_cf1 @ invert(res.T_cf2_from_cf1)})
    return _write(args, ctx, "stereo", models, {rig_id: rig}, reports)


def _board_depths(ctx: dict[str, Any], models: dict[str, Any], cid: str) -> list:
    from mvpose_core.calibration.intrinsics import board_pose

    return [
        board_pose(models[cid], d, ctx["board"]) for d in ctx["dets"][cid].values() if d is not None
    ]


def _step_handeye(args: argparse.Namespace) -> int:
    from mvpose_core.calibration.errors import CalibrationError
    from mvpose_core.calibration.handeye import HandEyeOptions, build_problem, calibrate_handeye
    from mvpose_core.calibration.report import handeye_report, stereo_report
    from mvpose_core.calibration.robotposes import load_robot_poses
    from mvpose_core.calibration.stereo import calibrate_stereo
    from mvpose_core.transforms import invert

    if args.poses is None:
        raise CliError("handeye needs --poses (robot flange pose per sample)")
    poses = load_robot_poses(args.poses, args.convention)
    ctx = _common(args)
    reports: list = []
    models = _intrinsics(ctx, args, reports)
    cams = list(ctx["dets"])
    ref = cams[0]
    rel = {ref: np.eye(4)}
    for other in cams[1:]:
        known = _rig_relation(ctx["base"], ref, other)
        if known is not None:
            rel[other] = known  # the stereo result of --base
            continue
        st = calibrate_stereo(
            ref,
            other,
            ctx["dets"][ref],
            ctx["dets"][other],
            ctx["board"],
            models[ref],
            models[other],
        )
        depth = float(np.median([T[2, 3] for T in _board_depths(ctx, models, ref)]))
        reports.append((stereo_report(st, depth), None))
        models[ref], models[other] = st.model1, st.model2
        rel[other] = st.T_cf2_from_cf1
    problem, rejected = build_problem("robot", ctx["board"], models, poses, ctx["dets"], rel)
    T_rf_from_bf = None
    if args.board_pose is not None:
        bp = load_robot_poses(args.board_pose, args.convention)
        if "board" not in bp:
            raise CliError(f"{args.board_pose}: expected one pose with id 'board', got {list(bp)}")
        T_rf_from_bf = bp["board"]
    # Intrinsics taken from --base were chosen by the engineer: hold them. Otherwise adjust them
    # with the hand-eye: the images hold their information, the robot poses are weighted.
    from_base = ctx["base"] is not None and all(c in ctx["base"].cameras for c in cams)
    mm, deg = _robot_sigma(args, ctx["station"])
    opt = HandEyeOptions(
        refine_intrinsics=not (from_base or args.fix_intrinsics),
        robot_sigma_mm=mm,
        robot_sigma_deg=deg,
    )
    try:
        res = calibrate_handeye(problem, opt, T_rf_from_bf=T_rf_from_bf, rejected=rejected)
    except CalibrationError as err:
        raise CliError(f"{args.poses}: {err}") from None
    reports = _as_start(reports, "hand-eye")
    reports.append((handeye_report(problem, res), res.residuals))
    models, rel = res.cameras, res.T_cfc_from_cf0
    rig_id, T_rig_from_ref = _rig_frame(ctx, args, ref, "robot")
    rig = _rig(
        res.X @ invert(T_rig_from_ref), None, {c: T_rig_from_ref @ invert(rel[c]) for c in cams}
    )
    return _write(args, ctx, "handeye", models, {rig_id: rig}, reports, poses_file=args.poses)


def _robot_sigma(args: argparse.Namespace, station: Any) -> tuple[float, float]:
    """The robot's per-axis 1σ: --robot-sigma, else the station file's (an RSS figure over
    three axes), else a good industrial robot's."""
    if args.robot_sigma is not None:
        mm, deg = args.robot_sigma
        if not (mm > 0 and deg > 0):
            raise CliError(f"--robot-sigma: both values must be > 0, got {mm:g} {deg:g}")
        return float(mm), float(deg)
    rep = station.uncertainty.robot_repeatability if station is not None else None
    if rep is not None and rep.mm > 0 and rep.deg > 0:
        return rep.mm / np.sqrt(3.0), rep.deg / np.sqrt(3.0)
    return 0.05, 0.01


def _step_station(args: argparse.Namespace) -> int:
    from mvpose_core.calibration.handeye import build_problem, calibrate_handeye
    from mvpose_core.calibration.report import station_report
    from mvpose_core.calibration.robotposes import load_robot_poses
    from mvpose_core.calibration.station import board_poses_from_robot, calibrate_station
    from mvpose_core.transforms import invert

    if args.station is None:
        raise CliError("station needs --station (which rigs are fixed and how they hold cameras)")
    if (args.poses is None) == (args.board_poses is None):
        raise CliError(
            "station needs either --board-poses (board measured in RF per sample) "
            "or --poses (board carried by the robot)"
        )
    ctx = _common(args)
    reports: list = []
    models = _intrinsics(ctx, args, reports)
    if args.board_poses is not None:
        T_rf_from_bf = load_robot_poses(args.board_poses, args.convention)
        src = args.board_poses
    else:
        poses = load_robot_poses(args.poses, args.convention)
        # The board's pose on the flange from the camera that sees it most often (eye-to-hand).
        best = max(ctx["dets"], key=lambda c: sum(d is not None for d in ctx["dets"][c].values()))
        problem, rejected = build_problem(
            "fixed", ctx["board"], {best: models[best]}, poses, {best: ctx["dets"][best]}
        )
        he = calibrate_handeye(problem, rejected=rejected)
        T_rf_from_bf = board_poses_from_robot(poses, he.Y)
        src = args.poses
    # Intrinsics from --base were chosen by the engineer: hold them (as the hand-eye does).
    from_base = ctx["base"] is not None and all(c in ctx["base"].cameras for c in models)
    res = calibrate_station(
        ctx["board"], models, ctx["dets"], T_rf_from_bf, refine_intrinsics=not from_base
    )
    residuals = {s: r for g in res.groups for s, r in g.residuals.items()}
    ref = next(iter(models))
    depth = float(np.median([T[2, 3] for T in _board_depths(ctx, models, ref)]))
    reports = _as_start(reports, "station adjustment")
    reports.append((station_report(res, depth, models[ref].fx), residuals))
    models = dict(res.cameras)  # adjusted with the relations: the file holds these
    station = ctx["station"]
    rigs = {}
    for rig in station.rigs:
        cams = [rc for rc in rig.cameras if rc.camera in res.T_rf_from_cf]
        if rig.mount != "fixed" or not cams:
            continue
        first = cams[0]
        T_rf_from_rig = res.T_rf_from_cf[first.camera] @ invert(first.T_rig_from_cf.matrix)
        rigs[rig.id] = _rig(
            None,
            T_rf_from_rig,
            {rc.camera: invert(T_rf_from_rig) @ res.T_rf_from_cf[rc.camera] for rc in cams},
        )
    return _write(args, ctx, "station", models, rigs, reports, poses_file=src)


def _as_start(reports: list, step: str) -> list:
    """The steps before wrote start values; the file holds the last step's, and says so."""
    return [
        (replace(r, kind=f"{r.kind}, start of the {step} (the file holds the values below)"), x)
        for r, x in reports
    ]


# --------------------------------------------------------------------------- outputs


def _rig_frame(
    ctx: dict[str, Any], args: argparse.Namespace, ref: str, mount: str, allow_any: bool = False
) -> tuple[str, np.ndarray]:
    """Rig id and the rig's nominal ``T_rig_from_cf`` of the reference camera (kept, so the rig
    frame means what the station file says it means); identity without a station."""
    station = ctx["station"]
    if station is None:
        return args.rig or "rig", np.eye(4)
    rig = station.rig_of(ref)
    if args.rig and args.rig != rig.id:
        raise CliError(f"camera {ref!r} is in rig {rig.id!r}, not {args.rig!r}")
    if rig.mount != mount and not allow_any:
        raise CliError(f"rig {rig.id!r} is {rig.mount}-mounted; this step calibrates {mount} rigs")
    T = next(rc.T_rig_from_cf.matrix for rc in rig.cameras if rc.camera == ref)
    return rig.id, T


def _rig_relation(base: Any, ref: str, other: str) -> np.ndarray | None:
    """``T_cfo_from_cfref`` from an earlier calibration's rig holding both cameras, if any."""
    if base is None:
        return None
    for rig in base.rigs.values():
        poses = rig.T_rig_from_cf
        if ref in poses and other in poses:
            return np.linalg.inv(poses[other].matrix) @ poses[ref].matrix
    return None


def _rig(T_gf_from_rig: Any, T_rf_from_rig: Any, T_rig_from_cf: dict[str, Any]) -> Any:
    from mvpose_core.calibration.files import RigCalibration, pose

    return RigCalibration(
        T_gf_from_rig=pose(T_gf_from_rig) if T_gf_from_rig is not None else None,
        T_rf_from_rig=pose(T_rf_from_rig) if T_rf_from_rig is not None else None,
        T_rig_from_cf={c: pose(T) for c, T in T_rig_from_cf.items()},
    )


def _write(
    args: argparse.Namespace,
    ctx: dict[str, Any],
    kind: str,
    models: dict[str, Any],
    rigs: dict[str, Any],
    reports: list,
    poses_file: Path | None = None,
) -> int:
    from mvpose_core.calibration.files import (
        CameraCalibration,
        InputsSummary,
        make_calibration,
        merge,
        save_calibration,
    )
    from mvpose_core.calibration.report import save_residual_plot

    used = sorted({s for r, _ in reports for s in r.per_sample_rms_px})
    rejected: dict[str, str] = {}
    for r, _ in reports:
        rejected.update(r.rejected)
    inputs = InputsSummary(
        board=str(ctx["board"]),
        images=str(args.images),
        robot_poses=str(poses_file or ""),
        robot_poses_sha256=_sha256(poses_file) if poses_file else "",
        robot_convention=getattr(args, "convention", None) or "",
        samples_used=used,
        samples_rejected=rejected,
        based_on=ctx["base"].ref if ctx["base"] is not None else None,
    )
    cams, rigs = merge(
        ctx["base"], {c: CameraCalibration.from_model(m) for c, m in models.items()}, rigs
    )
    station = ctx["station"].name if ctx["station"] is not None else None
    calib = make_calibration(
        kind, inputs, cams, rigs, {r.kind: r.to_dict() for r, _ in reports}, station=station
    )
    out: Path = args.out
    save_calibration(out, calib)
    text = "\n".join(r.text() for r, _ in reports)
    out.with_suffix(".report.txt").write_text(text + "\n")
    last, residuals = reports[-1]
    save_residual_plot(out.with_suffix(".residuals.png"), last, residuals)
    print(text)
    print(f"wrote {out} (id {calib.id}, sha256 {calib.sha256[:12]}…)")
    return 0


_STEPS = {
    **rehearsal.STEPS,
    **rehearse_robot.STEPS,
    "intrinsics": _step_intrinsics,
    "stereo": _step_stereo,
    "handeye": _step_handeye,
    "station": _step_station,
}
