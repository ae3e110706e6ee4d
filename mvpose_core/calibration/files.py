"""Versioned calibration files: id, time, content hash, inputs; load, save, apply to a station.

A calibration file is JSON. Its ``sha256`` is the hash of the canonical JSON (sorted keys, no
whitespace, UTF-8) of every other field, so the hash does not depend on formatting and any edit
of the content is detected on load. The server records a :class:`CalibrationRef` (id, sha256)
with every measurement.
"""

from __future__ import annotations

import hashlib
import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from mvpose_core.camera import CameraModel
from mvpose_core.station import Intrinsics, Pose, StationConfig
from mvpose_core.transforms import Array

FORMAT: Literal["mvpose-calibration/1"] = "mvpose-calibration/1"


class CalibrationFileError(ValueError):
    """A calibration file cannot be read or used; the message names the file and the problem."""


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CalibrationRef(_Model):
    """Which calibration produced a measurement."""

    id: str
    sha256: str


class CameraCalibration(_Model):
    intrinsics: Intrinsics
    distortion: list[float]
    image_size: tuple[int, int]

    @classmethod
    def from_model(cls, m: CameraModel) -> CameraCalibration:
        return cls(
            intrinsics=Intrinsics(fx=m.fx, fy=m.fy, cx=m.cx, cy=m.cy),
            distortion=[float(x) for x in m.dist],
            image_size=(m.width, m.height),
        )


class RigCalibration(_Model):
    """Extrinsics of one rig; exactly one of the mount poses is set."""

    T_gf_from_rig: Pose | None = None
    T_rf_from_rig: Pose | None = None
    T_rig_from_cf: dict[str, Pose] = Field(default_factory=dict)


class InputsSummary(_Model):
    """What the calibration was computed from, enough to find and repeat it."""

    board: str
    images: str = ""
    robot_poses: str = ""
    robot_poses_sha256: str = ""
    robot_convention: str = ""
    samples_used: list[str] = Field(default_factory=list)
    samples_rejected: dict[str, str] = Field(default_factory=dict)
    based_on: CalibrationRef | None = None


class CalibrationFile(_Model):
    format: Literal["mvpose-calibration/1"] = FORMAT
    id: str
    created: str
    kind: Literal["intrinsics", "stereo", "handeye", "station"]
    station: str | None = None
    inputs: InputsSummary
    cameras: dict[str, CameraCalibration] = Field(default_factory=dict)
    rigs: dict[str, RigCalibration] = Field(default_factory=dict)
    report: dict[str, Any] = Field(default_factory=dict)
    sha256: str = ""

    @property
    def ref(self) -> CalibrationRef:
        return CalibrationRef(id=self.id, sha256=self.sha256)

    def content_hash(self) -> str:
        return content_hash(self.model_dump(mode="json", exclude={"sha256"}))


def canonical_json(data: Any) -> str:
    """Key-sorted, whitespace-free JSON: the text the content hash is computed over."""
    return json.dumps(
        data, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False
    )


def content_hash(data: Any) -> str:
    return hashlib.sha256(canonical_json(data).encode("utf-8")).hexdigest()


def make_calibration(
    kind: str,
    inputs: InputsSummary,
    cameras: dict[str, CameraCalibration] | None = None,
    rigs: dict[str, RigCalibration] | None = None,
    report: dict[str, Any] | None = None,
    station: str | None = None,
    created: datetime | None = None,
) -> CalibrationFile:
    """A new calibration with its id (station, kind, UTC time) and content hash."""
    when = (created or datetime.now(UTC)).astimezone(UTC)
    stamp = when.strftime("%Y%m%dT%H%M%SZ")
    draft = CalibrationFile(
        id=f"{station or 'calibration'}-{kind}-{stamp}",
        created=when.isoformat(timespec="seconds"),
        kind=kind,
        station=station,
        inputs=inputs,
        cameras=cameras or {},
        rigs=rigs or {},
        report=_jsonable(report or {}),
    )
    return draft.model_copy(update={"sha256": draft.content_hash()})


def _jsonable(obj: Any) -> Any:
    """Numpy scalars and arrays to plain JSON values (NaN is not JSON: it becomes null)."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def save_calibration(path: str | Path, calib: CalibrationFile) -> Path:
    """Write a calibration file (indented JSON; the hash does not depend on the layout)."""
    if calib.sha256 != calib.content_hash():
        raise CalibrationFileError(f"calibration {calib.id!r}: sha256 does not match its content")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(calib.model_dump(mode="json"), indent=2, sort_keys=True) + "\n")
    return path


def load_calibration(path: str | Path) -> CalibrationFile:
    """Read a calibration file and verify its format and content hash."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise CalibrationFileError(
            f"{path}: cannot read calibration file: {err.strerror}"
        ) from None
    except json.JSONDecodeError as err:
        raise CalibrationFileError(f"{path}: not valid JSON: {err}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise CalibrationFileError(f"{path}: not an {FORMAT} file (format: {got!r})")
    try:
        calib = CalibrationFile.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(x) for x in first["loc"])
        raise CalibrationFileError(f"{path}: {where}: {first['msg']}") from None
    actual = calib.content_hash()
    if actual != calib.sha256:
        raise CalibrationFileError(
            f"{path}: content hash {actual[:12]}… does not match the recorded sha256 "
            f"{calib.sha256[:12]}…; the file was edited after it was written"
        )
    return calib


def merge(
    base: CalibrationFile | None,
    cameras: dict[str, CameraCalibration],
    rigs: dict[str, RigCalibration],
) -> tuple[dict[str, CameraCalibration], dict[str, RigCalibration]]:
    """The new results on top of an earlier calibration's (cameras and rigs by id)."""
    cams = dict(base.cameras) if base else {}
    cams.update(cameras)
    out_rigs = dict(base.rigs) if base else {}
    for rid, r in rigs.items():
        old = out_rigs.get(rid)
        poses = {**(old.T_rig_from_cf if old else {}), **r.T_rig_from_cf}
        out_rigs[rid] = r.model_copy(update={"T_rig_from_cf": poses})
    return cams, out_rigs


def pose(T: Array) -> Pose:
    return Pose.from_matrix(np.asarray(T, dtype=float))


# --------------------------------------------------------------------------- apply to a station


def apply_calibration(station: StationConfig, calib: CalibrationFile) -> StationConfig:
    """The station with the calibrated intrinsics, distortion and extrinsics put in."""
    data = station.model_dump(mode="python")
    cams = {c["id"]: c for c in data["cameras"]}
    for cid, cc in calib.cameras.items():
        if cid not in cams:
            raise CalibrationFileError(
                f"calibration {calib.id!r}: camera {cid!r} is not in station {station.name!r}"
            )
        if tuple(cams[cid]["image_size"]) != tuple(cc.image_size):
            raise CalibrationFileError(
                f"calibration {calib.id!r}: camera {cid!r} was calibrated at "
                f"{cc.image_size[0]}x{cc.image_size[1]} but the station says "
                f"{cams[cid]['image_size'][0]}x{cams[cid]['image_size'][1]}"
            )
        cams[cid]["intrinsics"] = cc.intrinsics.model_dump()
        cams[cid]["distortion"] = list(cc.distortion)
    rigs = {r["id"]: r for r in data["rigs"]}
    for rid, rc in calib.rigs.items():
        if rid not in rigs:
            raise CalibrationFileError(
                f"calibration {calib.id!r}: rig {rid!r} is not in station {station.name!r}"
            )
        rig = rigs[rid]
        if rc.T_gf_from_rig is not None:
            if rig["mount"] != "robot":
                raise CalibrationFileError(
                    f"calibration {calib.id!r}: rig {rid!r} has a hand-eye pose but is fixed"
                )
            rig["T_gf_from_rig"] = rc.T_gf_from_rig.model_dump()
        if rc.T_rf_from_rig is not None:
            if rig["mount"] != "fixed":
                raise CalibrationFileError(
                    f"calibration {calib.id!r}: rig {rid!r} has a base pose but is robot-mounted"
                )
            rig["T_rf_from_rig"] = rc.T_rf_from_rig.model_dump()
        in_rig = {c["camera"]: c for c in rig["cameras"]}
        for cid, p in rc.T_rig_from_cf.items():
            if cid not in in_rig:
                raise CalibrationFileError(
                    f"calibration {calib.id!r}: camera {cid!r} is not in rig {rid!r}"
                )
            in_rig[cid]["T_rig_from_cf"] = p.model_dump()
    unc = data.setdefault("uncertainty", {})
    unc["rigs"] = {**unc.get("rigs", {}), **report_rig_sigmas(calib)}
    return StationConfig.model_validate(data)


def report_rig_sigmas(calib: CalibrationFile) -> dict[str, dict[str, float]]:
    """1σ of each rig's mount pose from a hand-eye report (``{rig: {mm, deg}}``), for the
    station's uncertainty model (:class:`mvpose_core.uncertainty_settings.UncertaintyConfig`).

    The report's figures are of the reference camera's pose (``T_gf_from_cf`` or
    ``T_rf_from_cf``), RSS over the axes: the weighted adjustment's 1σ, which counts the robot
    pose errors. The jackknife beside it is a cross-check; it is taken instead only where it
    exceeds the adjustment's by more than its sampling spread allows (``JACKKNIFE_EXCESS``),
    i.e. where the data scatter more than the model says.
    """
    from mvpose_core.calibration.report import JACKKNIFE_EXCESS

    mounted = [
        rid
        for rid, r in calib.rigs.items()
        if r.T_gf_from_rig is not None or r.T_rf_from_rig is not None
    ]
    figures: dict[str, list[float]] = {"mm": [], "deg": []}
    for rep in calib.report.values():
        sigma = rep.get("sigma", {}) if isinstance(rep, dict) else {}
        for key, value in sigma.items():
            if not key.startswith(("T_gf_from_cf ", "T_rf_from_cf ")) or value is None:
                continue
            if "(jackknife)" in key:
                continue
            unit = "mm" if key.endswith(" translation mm") else "deg"
            v = float(value)
            jack = sigma.get(f"{key} (jackknife)")
            if jack is not None and float(jack) > JACKKNIFE_EXCESS * v:
                v = float(jack)
            figures[unit].append(v)
    if len(mounted) != 1 or not (figures["mm"] or figures["deg"]):
        return {}
    return {
        mounted[0]: {"mm": max(figures["mm"], default=0.0), "deg": max(figures["deg"], default=0.0)}
    }


def calibrated_station(
    station: StationConfig, station_path: str | Path | None = None
) -> tuple[StationConfig, CalibrationRef | None]:
    """The station with its ``calibration:`` file applied (a relative path is taken from the
    station file's folder), and the reference every measurement should record."""
    if station.calibration is None:
        return station, None
    path = Path(station.calibration)
    if not path.is_absolute() and station_path is not None:
        path = Path(station_path).parent / path
    calib = load_calibration(path)
    if calib.station is not None and calib.station != station.name:
        raise CalibrationFileError(
            f"{path}: calibration is for station {calib.station!r}, not {station.name!r}"
        )
    return apply_calibration(station, calib), calib.ref
