"""Recipes and calibrations endpoints: list, versions, one version, upload, activate."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any

from fastapi import APIRouter, Body, Path, Request
from pydantic import BaseModel, Field, StrictBool, ValidationError

from mvpose_core.station import RecipeConfig, StationConfig, parse_station
from server.api.deps import EngineerUser, ReadUser, ServicesDep
from server.errors import InvalidInputError
from server.state import recipe_content
from server.store.versions import Kind, VersionInfo, VersionSummary

NamePath = Annotated[str, Path(pattern=r"^[A-Za-z0-9_.\-]+$", max_length=64)]
VersionPath = Annotated[int, Path(ge=1, le=2**31 - 1)]


class VersionContent(BaseModel):
    info: VersionInfo
    content: dict[str, Any]


class VersionUpload(BaseModel):
    content: dict[str, Any] = Field(description="the recipe (station-file schema) or calibration")
    comment: str = Field("", max_length=400)
    # true/false only: pydantic's lax bool would also take 1, "yes" or "on"
    activate: StrictBool = Field(False, description="make the new version active at once")


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


def version_router(
    kind: Kind, check: Callable[[str, dict[str, Any], StationConfig | None], dict[str, Any]]
) -> APIRouter:
    plural = f"{kind}s"
    router = APIRouter(prefix=f"/{plural}", tags=[plural])

    @router.get("", response_model=list[VersionSummary], summary=f"List {plural}")
    def list_names(_: ReadUser, services: ServicesDep) -> list[VersionSummary]:
        """Every name with its newest and its active version."""
        return services.store.versions.names(kind)

    @router.get(
        "/{name}/versions", response_model=list[VersionInfo], summary=f"Versions of a {kind}"
    )
    def list_versions(name: NamePath, _: ReadUser, services: ServicesDep) -> list[VersionInfo]:
        """All versions, oldest first, with who made them and which is active."""
        return services.store.versions.versions(kind, name)

    @router.get("/{name}/active", response_model=VersionContent, summary=f"Active {kind}")
    def get_active(name: NamePath, _: ReadUser, services: ServicesDep) -> VersionContent:
        """The active version and its content."""
        info, content = services.store.versions.content(kind, name)
        return VersionContent(info=info, content=content)

    @router.get(
        "/{name}/versions/{version}", response_model=VersionContent, summary=f"One {kind} version"
    )
    def get_version(
        name: NamePath, version: VersionPath, _: ReadUser, services: ServicesDep
    ) -> VersionContent:
        """One version and its content."""
        info, content = services.store.versions.content(kind, name, version)
        return VersionContent(info=info, content=content)

    @router.post(
        "/{name}/versions",
        response_model=VersionInfo,
        status_code=201,
        summary=f"Upload a {kind} version",
    )
    def upload(
        request: Request,
        name: NamePath,
        upload: Annotated[VersionUpload, Body()],
        user: EngineerUser,
        services: ServicesDep,
    ) -> VersionInfo:
        """Store a new version (engineer); optionally activate it."""
        content = check(name, upload.content, services.station)
        info = services.store.versions.add(kind, name, content, user.name, upload.comment)
        if upload.activate:
            info = services.store.versions.activate(kind, name, info.version, user.name)
            _tell_station(request)
        return info

    @router.post(
        "/{name}/versions/{version}/activate",
        response_model=VersionInfo,
        summary=f"Activate a {kind} version",
    )
    def activate(
        request: Request, name: NamePath, version: VersionPath, user: EngineerUser,
        services: ServicesDep,
    ) -> VersionInfo:
        """Make this version the one the station uses from the next trigger on (engineer)."""
        info = services.store.versions.activate(kind, name, version, user.name)
        _tell_station(request)
        return info

    return router


recipes_router = version_router("recipe", check_recipe)
calibrations_router = version_router("calibration", check_calibration)


def _tell_station(request: Request) -> None:
    """The station picks an activated version up within a second by itself; this makes it now,
    so the next trigger measures with it."""
    station = getattr(request.app.state, "station", None)
    if station is not None:
        station.reload_recipes()
