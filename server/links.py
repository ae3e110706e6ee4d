"""The station file's ``links`` section, each block checked by its backend's own settings model.

mvpose_core keeps the section as raw data (it never imports drivers); the server, which loads the
file, validates it here, so a typo inside ``links.modbus`` or an unknown backend stops start-up
with a message naming the file and the field, as every other field of the file does.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from drivers.links import LinkSettingsError, link_settings
from mvpose_core.station import StationConfig, StationFileError, problem_line
from mvpose_core.station import load_station as _load_station


def check_links(station: StationConfig, source: str) -> dict[str, BaseModel]:
    """The station's link settings by backend name; StationFileError naming ``source``, the
    field and the value when a block does not fit its backend."""
    try:
        return link_settings(station.links)
    except LinkSettingsError as err:
        lines = [problem_line(source, where, msg, value) for where, msg, value in err.problems]
        raise StationFileError("\n".join(lines)) from None


def load_station(path: str | Path) -> StationConfig:
    """Read and validate a station YAML file, its links included."""
    station = _load_station(path)
    check_links(station, str(path))
    return station
