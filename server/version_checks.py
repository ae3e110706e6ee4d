"""What a recipe or calibration version must be before it is stored or activated.

Used by the REST uploads (server.api.versions) and by the station process when a link activates
a stored calibration (server.station.queries), so both check the same way.
"""

from __future__ import annotations

from typing import Any

from pydantic import ValidationError

from mvpose_core.station import RecipeConfig, StationConfig, parse_station
from server.errors import InvalidInputError
from server.state import recipe_content


def check_recipe(
    name: str, content: dict[str, Any], station: StationConfig | None
) -> dict[str, Any]:
    """Validate a recipe upload against the station-file schema and, if known, the station."""
    data = {**content, "name": content.get("name", name)}
    if data["name"] != name:
        raise InvalidInputError(f"recipe content names {data['name']!r} but the URL names {name!r}")
    data.pop("version", None)  # the store numbers versions
    try:
        recipe = RecipeConfig.model_validate(data)
    except ValidationError as err:
        raise InvalidInputError(
            f"recipe {name!r} is not valid: {_first(err)}",
            errors=[{"loc": [str(x) for x in e["loc"]], "msg": e["msg"]} for e in err.errors()],
        ) from None
    if station is not None:
        # The recipe must fit this station's cameras and views: re-check the whole station.
        others = [r.model_dump(mode="json") for r in station.recipes if r.name != name]
        whole = station.model_dump(mode="json") | {
            "recipes": [*others, recipe.model_dump(mode="json")]
        }
        parse_station(whole, f"recipe upload {name!r}")
    return recipe_content(recipe)


def check_calibration(
    name: str, content: dict[str, Any], station: StationConfig | None
) -> dict[str, Any]:
    """A calibration file (``mvpose calibrate`` writes them: docs/calibration.md) whose content
    hash matches its ``sha256`` and which fits this station; stored under the station's name,
    the one calibration the station measures with once activated."""
    from mvpose_core.calibration.files import CalibrationFile, apply_calibration

    if station is not None and name != station.name:
        raise InvalidInputError(
            f"calibration {name!r}: station {station.name!r} measures with the calibration "
            f"named after it; upload to /calibrations/{station.name}/versions")
    try:
        calib = CalibrationFile.model_validate(content)
    except ValidationError as err:
        raise InvalidInputError(
            f"calibration {name!r} is not a calibration file: {_first(err)}",
            errors=[{"loc": [str(x) for x in e["loc"]], "msg": e["msg"]} for e in err.errors()],
        ) from None
    try:
        actual = calib.content_hash()
    except ValueError as err:  # NaN or infinity somewhere in the file
        raise InvalidInputError(f"calibration {name!r}: content is not plain JSON ({err})") \
            from None
    if actual != calib.sha256:
        raise InvalidInputError(
            f"calibration {name!r}: content hash {actual[:12]}… does not match its sha256 "
            f"{calib.sha256[:12]}…: the file was edited after it was written")
    if station is not None:
        try:
            apply_calibration(station, calib)
        except (ValueError, KeyError) as err:
            raise InvalidInputError(f"calibration {name!r} does not fit station "
                                    f"{station.name!r}: {err}") from None
    return calib.model_dump(mode="json")


def _first(err: ValidationError) -> str:
    e = err.errors()[0]
    return f"{'.'.join(str(x) for x in e['loc'])}: {e['msg']}"
