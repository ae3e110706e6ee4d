"""The services the app holds while it runs (store, image archive, metrics) and how they open."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mvpose_core.station import RecipeConfig, StationConfig
from server.auth import ensure_access
from server.images import ImageArchive
from server.links import load_station
from server.metrics import Metrics
from server.settings import Settings
from server.store import Store, open_store
from server.store.schemas import MeasurementFilter, MeasurementRecord, StoredMeasurement

log = logging.getLogger(__name__)

STATION_FILE_AUTHOR = "station-file"


@dataclass
class Services:
    """Everything a request or the pipeline needs; built once at start-up, passed explicitly."""

    settings: Settings
    station: StationConfig | None
    store: Store
    images: ImageArchive
    metrics: Metrics
    software_version: str

    @property
    def station_name(self) -> str:
        return self.store.station

    def record_measurement(self, record: MeasurementRecord) -> StoredMeasurement:
        """Append the record durably, then count it. Blocking: call from a worker thread."""
        stored = self.store.measurements.insert(record)
        self.metrics.observe(record, stored.seq)
        return stored

    def close(self) -> None:
        self.store.close()


def open_services(settings: Settings, *, seed: bool = True, bootstrap: bool = True) -> Services:
    """Read the station file, open and migrate the store, seed recipes, ensure the bootstrap token.

    The station process seeds the recipes (``seed``); the API process ensures the bootstrap
    token (``bootstrap``); a process that is both does both.

    A malformed station file raises StationFileError naming file, field and value, which stops
    start-up. Blocking: the lifespan runs it in a worker thread.
    """
    station = load_station(settings.station) if settings.station else None
    name = station.name if station else settings.station_name
    store = open_store(settings.resolved_database_url, name, settings.sqlite_synchronous)
    if station is not None and station.plant is not None and station.plant.mqtt is not None:
        # every alarm transition, from either process, queues its message in the outbox
        store.alarms.topic = f"{station.plant.topic_prefix(station.name)}/alarms"
    try:
        if station is not None and seed:
            seed_recipes(store, station, str(settings.station))
            seed_calibration(store, station, settings.station)
        if bootstrap:  # the bootstrap token, or a warning when nobody could log in
            secret = settings.bootstrap_token
            ensure_access(store.tokens, secret.get_secret_value() if secret else None)
        images = ImageArchive(
            settings.resolved_images_dir,
            store.images,
            settings.images_ok_every,
            int(settings.images_quota_mb * 1024 * 1024),
        )
        metrics = Metrics()
        last = store.measurements.page(MeasurementFilter(), None, 1)[0]
        metrics.chain_head.set(last[0].seq if last else 0)
    except Exception:
        store.close()
        raise
    return Services(
        settings=settings,
        station=station,
        store=store,
        images=images,
        metrics=metrics,
        software_version=settings.resolved_software_version,
    )


def recipe_content(recipe: RecipeConfig) -> dict[str, Any]:
    """What a recipe version stores: everything but ``version``, which the store assigns."""
    return recipe.model_dump(mode="json", exclude={"version"})


def seed_recipes(store: Store, station: StationConfig, source: str) -> None:
    """Store each station-file recipe as a version unless that exact content is stored already.

    A recipe whose file content is new (first start, or the file was edited) is activated; an
    unchanged file leaves the active version alone, so a reference taught since survives restarts.
    """
    for recipe in station.recipes:
        content = recipe_content(recipe)
        if store.versions.find("recipe", recipe.name, content) is None:
            info = store.versions.add(
                "recipe", recipe.name, content, STATION_FILE_AUTHOR, comment=f"from {source}"
            )
            store.versions.activate("recipe", recipe.name, info.version, STATION_FILE_AUTHOR)
            log.info(
                "recipe %s: station file content stored as version %d (active)",
                recipe.name,
                info.version,
            )


def station_calibration_file(station: StationConfig, station_file: Path | None) -> Path | None:
    """The station file's ``calibration:`` path (relative paths: from the station file)."""
    if not station.calibration:
        return None
    path = Path(station.calibration)
    if not path.is_absolute() and station_file is not None:
        path = Path(station_file).parent / path
    return path


def seed_calibration(store: Store, station: StationConfig, station_file: Path | None) -> None:
    """Store the station file's calibration file as a version of the calibration named after the
    station, unless that exact content is stored already; a new file content is activated.

    The store's active version of that calibration is what the station measures with (one
    source of truth): a calibration uploaded and activated over REST replaces the file's until
    the file's content changes. A missing or tampered file stops start-up, naming the file.
    """
    from mvpose_core.calibration.files import load_calibration

    path = station_calibration_file(station, station_file)
    if path is None:
        return
    calib = load_calibration(path)
    content = calib.model_dump(mode="json")
    if store.versions.find("calibration", station.name, content) is None:
        info = store.versions.add("calibration", station.name, content, STATION_FILE_AUTHOR,
                                  comment=f"from {path}")
        store.versions.activate("calibration", station.name, info.version, STATION_FILE_AUTHOR)
        log.info("calibration %s (%s): file content stored as version %d (active)",
                 station.name, calib.id, info.version)
