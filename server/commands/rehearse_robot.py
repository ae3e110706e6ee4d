"""``mvpose calibrate rehearse-handeye`` and ``rehearse-verify``: the robot-driven hand-eye and
the calibration verify of a station rehearsed on simulated cameras, through the PLC twin.

``rehearse-handeye`` starts the station (its cameras simulated, at the synthetic set's image
size, with the set's board as ``calibration_board``: ``<data dir>/station.yaml``), shows the
cameras the set's images pose by pose and plays the robot program over the PLC twin
(:mod:`server.handeye_rehearsal`): HANDEYE_BEGIN, HANDEYE_ADD_POSE per pose with the pose the
robot reported, HANDEYE_CALCULATE. It prints every answer, the stored calibration version
(waiting for activation) with its report and hold-out figures, and the result against the
set's truth. ``rehearse-verify`` starts that station again on the same store, activates the
version over REST, puts the simulated part at its taught reference and verifies the calibration.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import secrets
import sys
from pathlib import Path
from typing import Any

from server.cli import CliError
from server.commands.rehearsal import rig_against_truth, scale_cameras


def add_parsers(sub: Any) -> None:
    from server.plc_buses import BUSES

    text = ("the robot-driven hand-eye on simulated cameras: the station shows a synthetic set's "
            "images pose by pose, the PLC twin sends the begin, each pose and the calculate")
    p = sub.add_parser("rehearse-handeye", help=text, description=text)
    p.add_argument("--station", type=Path, required=True,
                   help="station YAML the set was rendered for (its cameras simulated)")
    p.add_argument("--set", type=Path, required=True, dest="set_dir", metavar="SET",
                   help="folder of `mvpose calibrate synthetic` (images, poses.csv, truth.json)")
    p.add_argument("--holdout", type=int, default=3,
                   help="poses held out to check the result (default %(default)s)")
    for q in (p, _verify_parser(sub)):
        q.add_argument("--data-dir", type=Path, required=True,
                       help="the station's store, session folders and station file")
        q.add_argument("--link", choices=sorted(BUSES), default="modbus",
                       help="the fieldbus between the PLC twin and the station (default modbus)")
        q.add_argument("--seed", type=int, default=1, help="random seed (default 1)")


def _verify_parser(sub: Any) -> Any:
    text = ("activate a calibration version and verify it: the simulated part at its taught "
            "reference, measured through the PLC twin, its 6-DoF difference and pass/fail")
    p = sub.add_parser("rehearse-verify", help=text, description=text)
    p.add_argument("--station", type=Path, required=True,
                   help="station YAML (rehearse-handeye's <data dir>/station.yaml)")
    p.add_argument("--activate", type=int, metavar="VERSION",
                   help="activate this calibration version first (default: verify the active)")
    return p


def _settings(station: Path, data_dir: Path) -> Any:
    from server.settings import Settings

    token = os.environ.get("MVPOSE_BOOTSTRAP_TOKEN") or "mvp_rehearsal-" + secrets.token_urlsafe(18)
    return Settings(station=station, data_dir=data_dir, bootstrap_token=token)


def _station_file(src: Path, truth: dict[str, Any], dst: Path) -> None:
    """``src`` with its cameras at the set's image size and the set's board for the sessions."""
    import yaml

    try:
        data = yaml.safe_load(src.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise CliError(f"--station {src}: {err}") from None
    if data.get("name") != truth["station"]:
        raise CliError(f"--set: rendered for station {truth['station']!r}, --station {src} is "
                       f"{data.get('name')!r}")
    scale_cameras(data, float(truth["image_scale"]))
    data["calibration_board"] = truth["board"]
    dst.parent.mkdir(parents=True, exist_ok=True)
    dst.write_text(f"# {src.name} at {truth['image_scale']:g} × its image size with the board "
                   "of the rehearsal's set (mvpose calibrate rehearse-handeye)\n"
                   + yaml.safe_dump(data, sort_keys=False))


def _step_handeye(args: argparse.Namespace) -> int:
    from mvpose_core.station import StationFileError
    from server.handeye_rehearsal import RehearsalSet

    if not 0 <= args.holdout <= 50:
        raise CliError(f"--holdout must be 0..50, got {args.holdout}")
    try:
        rset = RehearsalSet.load(args.set_dir)
    except ValueError as err:
        raise CliError(f"--set: {err}") from None
    path = args.data_dir / "station.yaml"
    _station_file(args.station, rset.truth, path)
    try:
        return asyncio.run(_handeye(args, rset, _settings(path, args.data_dir)))
    except (StationFileError, ValueError) as err:
        raise CliError(str(err)) from None


async def _handeye(args: argparse.Namespace, rset: Any, settings: Any) -> int:
    from mvpose_core.calibration.files import CalibrationFile
    from mvpose_core.calibration.session import HandEyeCode
    from server.handeye_rehearsal import FIGURES, PlcHandEye, show_pose
    from server.loopback import running_station
    from server.station.core import StationOptions

    def said(code: int) -> str:
        names = {int(c): c.name for c in HandEyeCode}
        return f"{code} {names[code]}" if code in names else str(code)

    print(f"starting station {settings.station} on simulated cameras ...", flush=True)
    async with running_station(settings, StationOptions(sim_seed=args.seed), http_port=None,
                               link=args.link, twin_poll_s=0.002) as lb:
        rt = lb.runtime
        assert rt.active is not None and rt.services is not None and lb.bus is not None
        conv = rt.active.config.robot_convention
        if conv is not rset.convention:
            raise CliError(f"--set: poses.csv is in the {rset.convention.value} convention, "
                           f"recipe {rt.active.config.name!r} in {conv.value}: render the set "
                           f"with --convention {conv.value}")
        w, h = rt.station.cameras[0].image_size
        bus = " ".join(lb.bus.describe(rt).split())
        print(f"station {rt.station.name}: cameras {', '.join(rset.cameras)} simulated at "
              f"{w} × {h}, board {rset.truth['board']}; the PLC twin on {bus}")
        plc = PlcHandEye(lb.twin, conv)

        def message() -> str:
            last = rt.handeye.status()["last"] or {}
            return str(last.get("message", ""))

        code, _ = await plc.begin(args.holdout)
        print(f"HANDEYE_BEGIN (hold out {args.holdout}): {said(code)}")
        if code:
            print(f"  {message()}")
            return 1
        for sid, pose in rset.poses.items():
            await asyncio.to_thread(show_pose, rt, rset, sid)
            code, out = await plc.add(pose)
            values = " ".join(f"{v:.3f}" for v in pose)
            print(f"HANDEYE_ADD_POSE {sid} ({values}): {said(code)}, poses held: {out['poses']}")
            if code:
                print(f"  {message()}")
        code, out = await plc.calculate()
        print(f"HANDEYE_CALCULATE: {said(code)}")
        print(f"  {message()}")
        if code:
            return 1
        version = out["version"]
        info, content = rt.services.store.versions.content("calibration", rt.station.name,
                                                           version)
        calib = CalibrationFile.model_validate(content)
        figures = dict(zip(FIGURES, (out[k] for k in FIGURES), strict=True))
        print(f"calibration {rt.station.name} version {version}: "
              f"{'active' if info.active else 'stored, not active (an engineer activates it)'}")
        print(f"  1σ hand-eye {figures['sigma_mm']:.3g} mm / {figures['sigma_deg']:.2g}°; "
              f"hold-out ({len(calib.report.get('hold-out', {}))} poses): reprojection RMS "
              f"{figures['holdout_rms_px']:.2f} px, flange pose up to "
              f"{figures['holdout_mm']:.2f} mm / {figures['holdout_deg']:.3f}°")
        folder = Path(rt.handeye.status()["folder"])
        print(f"report ({folder / 'report.txt'}):")
        for line in (folder / "report.txt").read_text().splitlines():
            print(f"  {line}")
        print(f"against the truth ({rset.root / 'truth.json'}):")
        deg, mm = rset.error(calib)
        print(f"T_gf_from_rig is {mm:.3f} mm / {deg:.4f}° from the truth")
        for line in rig_against_truth(calib, rset.truth):
            print(line)
    sys.stdout.flush()
    return 0


def _step_verify(args: argparse.Namespace) -> int:
    from mvpose_core.station import StationFileError

    if not args.station.is_file():
        raise CliError(f"--station {args.station}: no such file (rehearse-handeye writes "
                       "<data dir>/station.yaml)")
    try:
        return asyncio.run(_verify(args, _settings(args.station, args.data_dir)))
    except (StationFileError, ValueError) as err:
        raise CliError(str(err)) from None


async def _verify(args: argparse.Namespace, settings: Any) -> int:
    import httpx

    from drivers.links.layout import Status
    from server.loopback import running_station, trigger
    from server.station.core import StationOptions

    print(f"starting station {settings.station} on simulated cameras ...", flush=True)
    async with running_station(settings, StationOptions(sim_seed=args.seed), http_port=0,
                               link=args.link, twin_poll_s=0.002) as lb:
        rt = lb.runtime
        assert rt.active is not None and lb.base_url is not None  # started
        token = settings.bootstrap_token.get_secret_value()
        async with httpx.AsyncClient(base_url=f"{lb.base_url}/api/v1", timeout=300,
                                     headers={"Authorization": f"Bearer {token}"}) as api:

            async def call(method: str, url: str, body: Any = None, quiet: bool = False
                           ) -> dict[str, Any]:
                shown = f" {json.dumps(body)}" if body is not None else ""
                r = await api.request(method, url, json=body)
                if not quiet:
                    print(f"{method} /api/v1{url}{shown}: {r.status_code}")
                if r.status_code != 200:
                    try:
                        why = r.json().get("detail") or r.text
                    except ValueError:
                        why = r.text
                    raise CliError(f"{method} /api/v1{url}: {r.status_code} {why}")
                answer: dict[str, Any] = r.json()
                return answer

            if args.activate is not None:
                info = await call("POST", f"/calibrations/{rt.station.name}/versions/"
                                  f"{args.activate}/activate")
                print(f"  calibration {rt.station.name} version {info['version']} active: "
                      f"{info['active']}")
            recipe = rt.active.config
            await asyncio.to_thread(rt.scene.set_part_pose, recipe.T_rf_from_pf0.matrix)
            views = sorted({s.view for s in recipe.sightings})
            print(f"the simulated part {recipe.name} at its taught reference")
            if len(views) == 1:  # the station's verify measures it (PLC command VERIFY alike)
                report = await call("POST", "/calibration/verify")
            else:
                # A robot-mounted rig verifies by triggering its views (the robot moves), then
                # the verify judges that measurement.
                seq = 0
                for view in views:
                    rt.scene.set_view(view)
                    st, _ = await trigger(lb.twin, recipe, 1, None, view_index=view,
                                          part_id="VERIFY", timeout=60)
                    if st.has(Status.RESULT_VALID):
                        print(f"trigger view {view} (part id VERIFY): result {st.result_id}, "
                              f"code {st.result_code}")
                    else:
                        print(f"trigger view {view} (part id VERIFY): view done")
                    seq = st.result_id
                mid = await _measurement_id(call, seq)
                report = await call("POST", "/calibration/verify", {"measurement_id": mid})
    off = report["offset"]
    labels = " ".join(_labels(off["convention"]))
    values = " ".join(f"{v:.4f}" for v in off["values"])
    print(f"  difference to the taught pose ({off['convention']} {labels}): {values}")
    print(f"  at the grasp point: {report['grasp_displacement_mm']:.3f} mm, "
          f"{report['rotation_deg']:.4f}° (limits {report['limit_mm']:g} mm, "
          f"{report['limit_deg']:g}°)")
    print(f"  {'PASSED' if report['passed'] else 'FAILED'}: {report['message']}")
    sys.stdout.flush()
    return 0 if report["passed"] else 1


async def _measurement_id(call: Any, seq: int) -> int:
    """The stored measurement of result ``seq``: the answer may reach the PLC before its
    record is committed (the store writer's queue), so ask until it is there (up to 60 s)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 60.0
    while True:
        page = await call("GET", "/measurements?part_id=VERIFY&limit=1", quiet=True)
        items = [m for m in page["items"] if m["seq"] == seq]
        if items:
            print(f"GET /api/v1/measurements?part_id=VERIFY&limit=1: measurement {items[0]['id']}")
            return int(items[0]["id"])
        if loop.time() > deadline:
            raise CliError(f"the verify's measurement (result {seq}) is not in the store")
        await asyncio.sleep(0.1)


def _labels(convention: str) -> list[str]:
    from mvpose_core.transforms import RobotConvention

    return list(RobotConvention(convention).labels)


STEPS = {"rehearse-handeye": _step_handeye, "rehearse-verify": _step_verify}
