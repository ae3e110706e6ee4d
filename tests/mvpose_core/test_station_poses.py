"""Station file poses: {xyz, wpr}, a 4x4 matrix or a named robot convention; exact round trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mvpose_core.station import Pose, StationFileError, dump_station, load_station, parse_station
from mvpose_core.transforms import RobotConvention, from_robot, to_robot, xyzwpr_to_matrix

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"


def raw(name: str) -> dict:
    return yaml.safe_load((STATIONS / f"{name}.yaml").read_text())


T_HANDEYE = xyzwpr_to_matrix([12.5, -80.25, 140.0, 179.0, -1.5, 91.25])


def test_matrix_form_is_used_exactly_and_written_back_unchanged() -> None:
    rows = [[float(x) for x in r] for r in T_HANDEYE]
    p = Pose.model_validate({"matrix": rows})
    assert np.array_equal(p.matrix, T_HANDEYE)  # bit for bit, nothing re-derived
    assert p.model_dump(mode="json") == {"matrix": rows}
    assert Pose.from_matrix(T_HANDEYE, "matrix") == p


@pytest.mark.parametrize("conv", list(RobotConvention))
def test_every_convention_reads_and_writes_its_own_values(conv: RobotConvention) -> None:
    values = [float(x) for x in to_robot(T_HANDEYE, conv)]
    p = Pose.model_validate({"convention": conv.value.upper(), "values": values})
    assert p.convention is conv
    assert np.array_equal(p.matrix, from_robot(values, conv))
    assert np.allclose(p.matrix, T_HANDEYE, atol=1e-9)
    assert p.model_dump(mode="json") == {"convention": conv.value, "values": values}
    assert Pose.from_matrix(T_HANDEYE, conv).model_dump(mode="json")["values"] == values


def test_station_with_every_form_round_trips_exactly(tmp_path: Path) -> None:
    data = raw("lab")
    rig = data["rigs"][0]
    T_old = load_station(STATIONS / "lab.yaml").rig(rig["id"]).T_gf_from_rig
    assert T_old is not None
    rig["T_gf_from_rig"] = {"matrix": [[float(x) for x in r] for r in T_old.matrix]}
    rig["cameras"][1]["T_rig_from_cf"] = {"convention": "ABB",
                                          "values": [100.0, 0.5, -0.25, 1.0, 0.0, 0.0, 0.0]}
    data["views"][0]["T_rf_from_gf"] = {"convention": "ur",
                                        "values": [1.2, 0.1, 0.9, 3.1, 0.05, 0.0]}
    data["recipes"][0]["T_pf_from_grasp"] = {"xyz": [0.0, 0.0, 150.0]}
    path = tmp_path / "forms.yaml"
    path.write_text(yaml.safe_dump(data))
    st = load_station(path)
    assert np.array_equal(st.rig(rig["id"]).T_gf_from_rig.matrix, T_old.matrix)  # type: ignore[union-attr]
    assert np.allclose(st.view(data["views"][0]["id"]).T_rf_from_gf.matrix[:3, 3],  # type: ignore[union-attr]
                       [1200.0, 100.0, 900.0])
    text = dump_station(st)
    again = parse_station(yaml.safe_load(text))
    assert again == st
    assert dump_station(again) == text
    written = yaml.safe_load(text)
    assert written["rigs"][0]["T_gf_from_rig"] == rig["T_gf_from_rig"]
    assert written["rigs"][0]["cameras"][1]["T_rig_from_cf"]["convention"] == "abb"
    assert written["recipes"][0]["T_pf_from_grasp"] == {"xyz": [0.0, 0.0, 150.0],
                                                        "wpr": [0.0, 0.0, 0.0]}


@pytest.mark.parametrize(
    ("pose", "words"),
    [
        ({"matrix": [[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]]},
         ["T_gf_from_rig", "not a proper rotation", "[0.0, 0.0, 2.0, 0.0]"]),
        ({"matrix": [[1, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]},
         ["T_gf_from_rig", "last row", "[0.0, 0.0, 1.0, 1.0]"]),
        ({"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 0]]},
         ["T_gf_from_rig.matrix[0]", "[1, 0, 0]"]),
        ({"convention": "kuka", "values": [1, 2, 3, 4, 5]},
         ["T_gf_from_rig", "kuka pose has 6 values", "[1.0, 2.0, 3.0, 4.0, 5.0]"]),
        ({"convention": "abb", "values": [1, 2, 3, 0, 0, 0, 0]},
         ["T_gf_from_rig", "zero or non-finite norm", "[1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 0.0]"]),
        ({"convention": "stäubli", "values": [1, 2, 3, 4, 5, 6]},
         ["T_gf_from_rig.convention", "'stäubli'", "fanuc"]),
        ({"xyz": [1, 2, 3], "matrix": np.eye(4).tolist()},
         ["T_gf_from_rig", "got ['xyz', 'matrix']"]),
        ({"convention": "fanuc"}, ["T_gf_from_rig", "got ['convention']"]),
        ({"xyz": [1, 2, float("nan")]}, ["T_gf_from_rig", "finite", "nan"]),
    ],
)
def test_bad_pose_names_file_field_and_value(pose: dict, words: list[str]) -> None:
    data = raw("lab")
    data["rigs"][0]["T_gf_from_rig"] = pose
    with pytest.raises(StationFileError) as err:
        parse_station(data, "lab-edited.yaml")
    msg = str(err.value)
    assert msg.startswith("lab-edited.yaml: rigs[0](")
    for w in words:
        assert w in msg, (w, msg)
