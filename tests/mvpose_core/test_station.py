"""Station model: the example files load, round-trip, and bad files name file, field and value."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from mvpose_core.station import StationFileError, dump_station, load_station, parse_station

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"
EXAMPLES = ["lab", "station1", "station2"]


def raw(name: str) -> dict:
    return yaml.safe_load((STATIONS / f"{name}.yaml").read_text())


@pytest.mark.parametrize("name", EXAMPLES)
def test_examples_load_and_round_trip(name: str) -> None:
    st = load_station(STATIONS / f"{name}.yaml")
    assert st.name == name
    again = parse_station(yaml.safe_load(dump_station(st)))
    assert again == st
    rec = st.recipe()
    assert rec.mark_positions().shape == (len(rec.marks), 3)


def test_lab_is_robot_mounted_with_two_views() -> None:
    st = load_station(STATIONS / "lab.yaml")
    assert st.robot_mounted and [v.id for v in st.views] == [1, 2]
    assert st.view_camera_ids(1) == ["left", "right"]


def test_unknown_key_names_file_and_field(tmp_path: Path) -> None:
    data = raw("lab")
    data["cameras"][0]["intrinsics"]["fxx"] = 1.0
    path = tmp_path / "typo.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(StationFileError) as err:
        load_station(path)
    msg = str(err.value)
    assert str(path) in msg and "cameras[0](left).intrinsics.fxx" in msg and "1.0" in msg


def test_bad_value_names_field_and_value() -> None:
    data = raw("station1")
    data["recipes"][0]["mark_diameter_mm"] = -4
    with pytest.raises(
        StationFileError, match=r"st1\.yaml: recipes\[0\]\(floor_panel\)\.mark_diameter_mm.*-4"
    ):
        parse_station(data, "st1.yaml")


def test_cross_references_are_checked() -> None:
    data = raw("lab")
    data["recipes"][0]["sightings"][0]["marks"] = ["M1", "M9"]
    with pytest.raises(StationFileError, match="unknown marks.*M9"):
        parse_station(data, "lab.yaml")
    data = raw("lab")
    data["views"][0]["rigs"] = ["nope"]
    with pytest.raises(StationFileError, match="unknown rig 'nope'"):
        parse_station(data, "lab.yaml")


def test_unreadable_and_invalid_yaml(tmp_path: Path) -> None:
    with pytest.raises(StationFileError, match="cannot read"):
        load_station(tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed")
    with pytest.raises(StationFileError, match="not valid YAML"):
        load_station(bad)


def test_pose_fields_are_named_transforms() -> None:
    st = load_station(STATIONS / "lab.yaml")
    T = st.recipe().T_rf_from_pf0.matrix
    assert np.allclose(T[:3, 3], [1650.0, 80.0, -300.0])
