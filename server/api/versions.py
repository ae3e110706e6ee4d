"""Recipes and calibrations endpoints: list, versions, one version, upload, activate."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any

from fastapi import APIRouter, Body, Path, Request
from pydantic import BaseModel, Field, StrictBool

from mvpose_core.station import StationConfig
from server.api.deps import EngineerUser, ReadUser, ServicesDep, station_of
from server.store.versions import Kind, VersionInfo, VersionSummary
from server.version_checks import check_calibration, check_recipe

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
    station = station_of(request.app)
    if station is not None:
        station.reload_recipes()
