"""Robot-pose files: every convention, CSV and JSON, and the errors commissioning meets."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mvpose_core.calibration.errors import CalibrationError
from mvpose_core.calibration.robotposes import parse_robot_poses
from mvpose_core.transforms import RobotConvention, make_transform, to_robot, zyx_to_matrix

POSES = {
    "a01": make_transform(zyx_to_matrix(10.0, -20.0, 175.0), [1200.0, -300.0, 900.0]),
    "a02": make_transform(zyx_to_matrix(-35.0, 5.0, -170.0), [1350.0, 120.0, 1010.0]),
}


def _csv(conv: RobotConvention, scale: float = 1.0) -> str:
    rows = [",".join(["id", *conv.labels])]
    for sid, T in POSES.items():
        v = to_robot(T, conv)
        v[:3] *= scale
        rows.append(sid + "," + ",".join(repr(float(x)) for x in v))
    return "\n".join(rows) + "\n"


@pytest.mark.parametrize("conv", list(RobotConvention))
def test_csv_in_every_convention(conv: RobotConvention) -> None:
    got = parse_robot_poses(_csv(conv), conv)
    assert list(got) == list(POSES)
    for sid, T in POSES.items():
        np.testing.assert_allclose(got[sid], T, atol=1e-9)


def test_json_mapping_and_list_forms() -> None:
    conv = RobotConvention.ABB
    as_map = {
        "convention": "abb",
        "poses": {s: to_robot(T, conv).tolist() for s, T in POSES.items()},
    }
    as_list = [{"id": s, "pose": to_robot(T, conv).tolist()} for s, T in POSES.items()]
    for text, given in ((json.dumps(as_map), None), (json.dumps(as_list), "abb")):
        got = parse_robot_poses(text, given)
        np.testing.assert_allclose(got["a02"], POSES["a02"], atol=1e-9)


def test_metres_where_mm_are_expected() -> None:
    with pytest.raises(CalibrationError, match="wrong unit.*looks like m"):
        parse_robot_poses(_csv(RobotConvention.FANUC, scale=0.001), "fanuc")


def test_mm_where_ur_expects_metres() -> None:
    with pytest.raises(CalibrationError, match="expects metres; the file looks like mm"):
        parse_robot_poses(_csv(RobotConvention.UR, scale=1000.0), "ur")


def test_errors_name_the_problem() -> None:
    with pytest.raises(CalibrationError, match="does not match the kuka convention"):
        parse_robot_poses(_csv(RobotConvention.FANUC), "kuka")
    with pytest.raises(CalibrationError, match="needs a robot convention"):
        parse_robot_poses(_csv(RobotConvention.FANUC), None)
    dup = _csv(RobotConvention.FANUC) + _csv(RobotConvention.FANUC).splitlines()[1] + "\n"
    with pytest.raises(CalibrationError, match="'a01' appears twice"):
        parse_robot_poses(dup, "fanuc")
    with pytest.raises(CalibrationError, match="file says convention 'abb' but 'kuka'"):
        parse_robot_poses(json.dumps({"convention": "abb", "poses": {}}), "kuka")
    with pytest.raises(CalibrationError, match="row 2: column Z is not a number: 'x'"):
        parse_robot_poses("id,X,Y,Z,W,P,R\na,1,2,x,4,5,6\n", "fanuc")


BAD_FILES = [
    # Another convention's header: the message says whose header it is.
    (
        "id,X,Y,Z,A,B,C\n1,1000,0,900,0,0,0\n",
        "fanuc",
        r"poses.csv: row 1: CSV header id,X,Y,Z,A,B,C \(that is the header of kuka\) does not "
        r"match the fanuc convention",
    ),
    (
        "id,X,Y,Z,W,P,R\n1,1000,0,900,0,0\n",
        "fanuc",
        r"poses.csv: row 2: 6 columns, the header has 7",
    ),
    (
        "id,X,Y,Z,W,P,R\n1,1000,0,900,0,0,0\n2,1000,0,900,0,0,nan\n",
        "fanuc",
        r"poses.csv: row 3 \(sample '2'\): fanuc pose contains NaN",
    ),
    (
        "id,X,Y,Z,q1,q2,q3,q4\n1,1000,0,900,0,0,0,0\n",
        "abb",
        r"poses.csv: row 2 \(sample '1'\): quaternion .* has zero or non-finite norm",
    ),
    (
        "id,X,Y,Z,W,P,R\n1,1000,0,900,0,0,0\n",
        "stäubli",
        r"poses.csv: unknown robot convention 'stäubli'; known: fanuc",
    ),
    (
        json.dumps(
            {
                "convention": "fanuc",
                "poses": {"1": [[1, 0, 0, 1000], [0, 1, 0, 0], [0, 0, -1, 900], [0, 0, 0, 1]]},
            }
        ),
        None,
        r"poses.csv: pose 1 \(sample '1'\): not a rigid transform: .* det R = -1",
    ),
    (
        json.dumps({"convention": "fanuc", "poses": {"1": [1000, 0, "x", 0, 0, 0]}}),
        None,
        r"poses.csv: pose 1 \(sample '1'\): not a list of numbers",
    ),
    (
        json.dumps({"convention": "fanuc", "poses": [{"id": "1"}]}),
        None,
        r"poses.csv: pose 1: needs 'id' and 'pose'",
    ),
]


@pytest.mark.parametrize(("text", "conv", "message"), BAD_FILES)
def test_malformed_files_answer_one_line_with_file_and_row(text, conv, message) -> None:
    with pytest.raises(CalibrationError, match=message) as err:
        parse_robot_poses(text, conv, "poses.csv")
    assert "\n" not in str(err.value)


def test_a_pose_may_be_a_matrix() -> None:
    T = POSES["a01"]
    poses = parse_robot_poses(json.dumps({"convention": "kuka", "poses": {"m": T.tolist()}}), None)
    np.testing.assert_allclose(poses["m"], T)


def test_the_example_in_the_calibration_guide_parses() -> None:
    from pathlib import Path

    guide = Path(__file__).resolve().parents[2] / "docs" / "calibration.md"
    text = guide.read_text()
    start = text.index("id,X,Y,Z,W,P,R\n001")
    block = text[start : text.index("```", start)]
    poses = parse_robot_poses(block, "fanuc")
    assert list(poses) == ["001", "002"]
    assert np.linalg.norm(poses["001"][:3, 3]) > 1000.0
