"""Shifts from the station file: which shift a moment is in, across midnight and DST."""

from datetime import UTC, datetime
from pathlib import Path

import pytest

from mvpose_core.shifts import DEFAULT_SHIFTS, Shift, shift_at, time_zone
from mvpose_core.station import StationFileError, load_station

ROOT = Path(__file__).resolve().parents[2]


def test_the_default_is_three_eight_hour_shifts_from_six_utc() -> None:
    utc = time_zone("UTC")
    w = shift_at(DEFAULT_SHIFTS, utc, datetime(2026, 11, 2, 5, 59, tzinfo=UTC))
    assert (w.name, w.start, w.end) == ("night", datetime(2026, 11, 1, 22, 0, tzinfo=UTC),
                                        datetime(2026, 11, 2, 6, 0, tzinfo=UTC))
    w = shift_at(DEFAULT_SHIFTS, utc, datetime(2026, 11, 2, 6, 0, tzinfo=UTC))
    assert (w.name, w.start.hour, w.end.hour) == ("early", 6, 14)
    w = shift_at(DEFAULT_SHIFTS, utc, datetime(2026, 11, 2, 23, 0, tzinfo=UTC))
    assert (w.name, w.end) == ("night", datetime(2026, 11, 3, 6, 0, tzinfo=UTC))


def test_shift_starts_are_plant_wall_clock_times_across_dst() -> None:
    berlin = time_zone("Europe/Berlin")
    two = (Shift(name="day", start="06:00"), Shift(name="night", start="18:00"))
    summer = shift_at(two, berlin, datetime(2026, 7, 1, 12, 0, tzinfo=UTC))
    winter = shift_at(two, berlin, datetime(2026, 12, 1, 12, 0, tzinfo=UTC))
    assert summer.start == datetime(2026, 7, 1, 4, 0, tzinfo=UTC)  # 06:00 CEST
    assert winter.start == datetime(2026, 12, 1, 5, 0, tzinfo=UTC)  # 06:00 CET
    # the night of the switch to winter time lasts 13 h
    n = shift_at(two, berlin, datetime(2026, 10, 25, 0, 0, tzinfo=UTC))
    assert (n.end - n.start).total_seconds() == 13 * 3600


def test_the_station_file_names_a_bad_shift_or_zone(tmp_path: Path) -> None:
    text = (ROOT / "deploy" / "stations" / "station1.yaml").read_text()
    station = load_station(ROOT / "deploy" / "stations" / "station1.yaml")
    assert [s.start for s in station.shifts] == ["06:00", "14:00", "22:00"]
    assert station.recipes[0].nok_streak_warning == 3
    for extra, words in (("time_zone: Mars/Olympus\n", "Mars/Olympus"),
                         ("shifts: [{name: a, start: '25:00'}]\n", "start"),
                         ("shifts: [{name: a, start: '06:00'}, {name: a, start: '07:00'}]\n",
                          "'a' is given twice")):
        bad = tmp_path / "bad.yaml"
        bad.write_text(text + extra)
        with pytest.raises(StationFileError, match=words):
            load_station(bad)
