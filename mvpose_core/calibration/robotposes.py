"""Robot poses for calibration: reading CSV/JSON in any robot convention, matching them to images
by sample id, and the plausibility checks (unit, pure translations, single rotation axis)."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable, Mapping
from itertools import combinations
from pathlib import Path

import numpy as np

from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.transforms import (
    Array,
    RobotConvention,
    from_robot,
    invert,
    matrix_to_rotvec,
)

#: An industrial flange never works within this distance of the robot base origin (mm).
_MIN_REACH_MM = 50.0
#: No industrial robot reaches this far (mm); a track-mounted one would need its own frame.
_MAX_REACH_MM = 20_000.0


def parse_robot_poses(
    text: str, convention: RobotConvention | str | None, source: str = "<memory>"
) -> dict[str, Array]:
    """Robot flange poses ``T_rf_from_gf`` by sample id, from CSV or JSON text.

    CSV: a header ``id,<labels of the convention>`` (e.g. ``id,X,Y,Z,W,P,R``), one row per pose.
    JSON: ``{"convention": "kuka", "poses": {"007": [X, Y, Z, A, B, C], ...}}`` or a list of
    ``{"id": ..., "pose": [...]}``; a pose may also be a 4×4 matrix (rows, mm). A convention
    given in the file must agree with ``convention``. Every error is one line naming the file,
    the row and the problem.
    """
    stripped = text.lstrip()
    if stripped.startswith(("{", "[")):
        rows, conv = _parse_json(stripped, convention, source)
    else:
        if convention is None:
            raise CalibrationError(f"{source}: a CSV robot-pose file needs a robot convention")
        conv = _convention(convention, source)
        rows = _parse_csv(text, conv, source)
    poses: dict[str, Array] = {}
    for where, sid, values in rows:
        if sid in poses:
            raise CalibrationError(f"{source}: {where}: sample id {sid!r} appears twice")
        try:
            poses[sid] = _pose(values, conv)
        except ValueError as err:
            raise CalibrationError(f"{source}: {where} (sample {sid!r}): {err}") from None
    if not poses:
        raise CalibrationError(f"{source}: no robot poses")
    check_units(poses, conv, source)
    return poses


def _convention(value: RobotConvention | str, source: str) -> RobotConvention:
    try:
        return RobotConvention(str(value).lower())
    except ValueError:
        known = ", ".join(c.value for c in RobotConvention)
        raise CalibrationError(
            f"{source}: unknown robot convention {value!r}; known: {known}"
        ) from None


def _pose(values: object, conv: RobotConvention) -> Array:
    """A pose vector of ``conv``, or a 4×4 matrix whose rotation must be a rotation."""
    arr = np.asarray(values, dtype=float)
    if arr.shape == (4, 4):
        if not np.all(np.isfinite(arr)):
            raise ValueError("the matrix holds NaN or infinite values")
        R = arr[:3, :3]
        dev = float(np.abs(R.T @ R - np.eye(3)).max())
        if dev > 1e-4 or np.linalg.det(R) < 0 or not np.allclose(arr[3], [0, 0, 0, 1]):
            raise ValueError(
                f"not a rigid transform: |RᵀR − I| = {dev:.2g}, det R = "
                f"{np.linalg.det(R):.4g}, last row {arr[3].tolist()}"
            )
        return arr
    return from_robot(arr.reshape(-1), conv)


def load_robot_poses(
    path: str | Path, convention: RobotConvention | str | None
) -> dict[str, Array]:
    """Read a robot-pose file (see :func:`parse_robot_poses`)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise CalibrationError(f"{path}: cannot read robot-pose file: {err.strerror}") from None
    except UnicodeDecodeError:
        raise CalibrationError(f"{path}: not a text file (CSV or JSON expected)") from None
    return parse_robot_poses(text, convention, str(path))


def _parse_csv(text: str, conv: RobotConvention, source: str) -> list[tuple[str, str, object]]:
    reader = csv.reader(io.StringIO(text))
    header = [h.strip() for h in next(reader, [])]
    expected = ["id", *conv.labels]
    if [h.lower() for h in header] != [h.lower() for h in expected]:
        others = [
            c.value
            for c in RobotConvention
            if [h.lower() for h in header] == [h.lower() for h in ["id", *c.labels]]
        ]
        hint = f" (that is the header of {' / '.join(others)})" if others else ""
        raise CalibrationError(
            f"{source}: row 1: CSV header {','.join(header)}{hint} does not match the "
            f"{conv.value} convention; expected {','.join(expected)}"
        )
    rows: list[tuple[str, str, object]] = []
    for lineno, row in enumerate(reader, start=2):
        if not row or all(not c.strip() for c in row):
            continue
        where = f"row {lineno}"
        if len(row) != len(expected):
            raise CalibrationError(
                f"{source}: {where}: {len(row)} columns, the header has {len(expected)} "
                f"({','.join(expected)})"
            )
        values = []
        for label, cell in zip(expected[1:], row[1:], strict=True):
            try:
                values.append(float(cell))
            except ValueError:
                raise CalibrationError(
                    f"{source}: {where}: column {label} is not a number: {cell.strip()!r}"
                ) from None
        rows.append((where, row[0].strip(), values))
    return rows


def _parse_json(
    text: str, convention: RobotConvention | str | None, source: str
) -> tuple[list[tuple[str, str, object]], RobotConvention]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as err:
        raise CalibrationError(f"{source}: not valid JSON: {err}") from None
    file_conv = data.get("convention") if isinstance(data, dict) else None
    if (
        file_conv is not None
        and convention is not None
        and _convention(file_conv, source) != _convention(convention, source)
    ):
        raise CalibrationError(
            f"{source}: file says convention {file_conv!r} but "
            f"{_convention(convention, source).value!r} was given"
        )
    conv_value = file_conv or convention
    if conv_value is None:
        raise CalibrationError(f"{source}: no robot convention in the file or on the command line")
    conv = _convention(conv_value, source)
    body = data.get("poses") if isinstance(data, dict) else data
    rows: list[tuple[str, str, object]] = []
    if isinstance(body, dict):
        items = list(body.items())
    elif isinstance(body, list):
        items = []
        for k, e in enumerate(body):
            if not isinstance(e, dict) or "id" not in e or "pose" not in e:
                raise CalibrationError(f"{source}: pose {k + 1}: needs 'id' and 'pose'")
            items.append((e["id"], e["pose"]))
    else:
        raise CalibrationError(f"{source}: expected 'poses' as a mapping or a list")
    for k, (sid, v) in enumerate(items):
        where = f"pose {k + 1}"
        try:
            values = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            raise CalibrationError(
                f"{source}: {where} (sample {str(sid)!r}): not a list of numbers: {v!r}"
            ) from None
        rows.append((where, str(sid), values))
    return rows, conv


def check_units(poses: Mapping[str, Array], conv: RobotConvention, source: str) -> None:
    """Flange positions all within a few cm of the base, or tens of metres away, are a length
    unit mix-up (metres where mm belong, or mm where a UR pose wants metres)."""
    reach = max(float(np.linalg.norm(T[:3, 3])) for T in poses.values())
    expects = "metres" if conv is RobotConvention.UR else "mm"
    if reach < _MIN_REACH_MM or reach > _MAX_REACH_MM:
        small = reach < _MIN_REACH_MM
        ur = conv is RobotConvention.UR
        looks = {(True, True): "km", (True, False): "mm", (False, True): "m"}.get((ur, small), "µm")
        raise CalibrationError(
            f"{source}: robot poses in the wrong unit? the farthest flange position is "
            f"{reach:.3f} mm from the base when read in the {conv.value} convention, which "
            f"expects {expects}; the file looks like {looks}"
        )


# --------------------------------------------------------------------------- matching, geometry


def match_ids(robot_poses: Mapping[str, Array], image_ids: Iterable[str], what: str) -> list[str]:
    """The sample ids, which must be the same on both sides (never paired by position)."""
    images = set(image_ids)
    poses = set(robot_poses)
    if images != poses:
        raise CalibrationError(
            f"{what}: images and robot poses do not match: {len(images)} images, {len(poses)} "
            f"poses; images without a pose: {sorted(images - poses)}; poses without an image: "
            f"{sorted(poses - images)}"
        )
    return sorted(images)


def check_motion(
    robot_poses: Mapping[str, Array],
    relative_poses: Mapping[str, Array],
    what: str,
    min_rotation_deg: float = 5.0,
    min_axis_spread_deg: float = 10.0,
) -> None:
    """Reject pose sets that cannot determine a hand-eye transform.

    ``relative_poses`` are the camera-board poses of the same ids (``T_cf_from_bf``); their
    translations are compared with the robot's to catch a unit mix-up that survived the
    reach check (e.g. a robot near its base).
    """
    ids = sorted(robot_poses)
    A = [robot_poses[i] for i in ids]
    rot = []
    axes = []
    for a, b in combinations(A, 2):
        rv = matrix_to_rotvec(a[:3, :3].T @ b[:3, :3])
        ang = float(np.degrees(np.linalg.norm(rv)))
        rot.append(ang)
        if ang > min_rotation_deg:
            axes.append(rv / np.linalg.norm(rv))
    largest = max(rot) if rot else 0.0
    if largest < min_rotation_deg:
        raise CalibrationError(
            f"{what}: the robot poses are (almost) pure translations: the largest rotation "
            f"between two poses is {largest:.2f}°; the hand-eye rotation needs rotations of "
            f"more than {min_rotation_deg:g}° about at least two different axes"
        )
    spread = (
        max(
            float(np.degrees(np.arccos(np.clip(abs(float(u @ v)), 0.0, 1.0))))
            for u, v in combinations(axes, 2)
        )
        if len(axes) > 1
        else 0.0
    )
    if spread < min_axis_spread_deg:
        raise CalibrationError(
            f"{what}: every robot rotation is about one axis (axes within {spread:.1f}°); the "
            "hand-eye translation along that axis cannot be determined — tilt about two axes"
        )
    # Compare how far the robot and the camera-board relation move between samples.
    rob = [np.linalg.norm(a[:3, 3] - b[:3, 3]) for a, b in combinations(A, 2)]
    B = [invert(relative_poses[i])[:3, 3] for i in ids]
    cam = [np.linalg.norm(a - b) for a, b in combinations(B, 2)]
    ratio = float(np.median(rob) / max(float(np.median(cam)), 1e-9))
    if ratio < 0.05 or ratio > 20.0:
        raise CalibrationError(
            f"{what}: the robot moves {ratio:.4g}× as far as the camera sees the board move "
            "(median over pose pairs); robot poses in the wrong unit (metres vs mm) or a wrong "
            "board square size?"
        )
