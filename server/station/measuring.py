"""What the station measures with: the station model under its active calibration, the cameras,
the pipeline, the recipe book, the robot-mounted view sequence and an armed teach.

Changes (a calibration or recipe version activated elsewhere, a recipe selected, a reference
taught) are made on the trigger thread between triggers (server.station.triggers runs them
there), so a measurement never sees its recipe or calibration change under it.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import replace
from typing import Any

import numpy as np

from drivers.cameras import CaptureGroup, make_camera
from mvpose_core.station import StationConfig
from server.pipeline import Pipeline
from server.recipes import ActiveRecipe, RecipeBook
from server.state import Services
from server.station.options import StationOptions
from server.station.records import Provenance
from server.station.sequence import ViewSequence
from server.store.schemas import MeasurementRecord

log = logging.getLogger(__name__)


class Measuring:
    """The station's measuring equipment and its recipe and calibration state."""

    def __init__(self, station: StationConfig, options: StationOptions) -> None:
        self.file_station = station  # as the station file says, before any calibration
        self.station = station
        self.options = options
        self.calibration_version: int | None = None
        self.services: Services | None = None
        self.scene: Any = None  # drivers.cameras.SimScene when the station has sim cameras
        self.capture: CaptureGroup | None = None
        self.pipeline: Pipeline | None = None
        self.book: RecipeBook | None = None
        self.sequence: ViewSequence | None = None
        self.provenance: Provenance | None = None
        self.warmed_ms: dict[str, float] = {}
        self.teach_armed_by: str | None = None

    # ------------------------------------------------------------------ life cycle
    def open(self, services: Services) -> None:
        """Apply the active calibration, load the recipes, open the cameras, warm up."""
        self.services = services
        calib = self._apply_calibration()
        self.provenance = Provenance(self.station.name, services.software_version, calib)
        self.book = RecipeBook(self.station, services.store)
        self._open_cameras()
        assert self.capture is not None
        self.pipeline = Pipeline(self.station, self.capture, options=self.options.pipeline)
        for recipe in self.book.recipes.values():
            t = time.monotonic()
            try:
                self.pipeline.warm_up(recipe.config)
            except Exception:  # a recipe the engine cannot measure still fails its triggers
                log.warning("recipe %s: warm-up failed", recipe.config.name, exc_info=True)
                continue
            self.warmed_ms[recipe.config.name] = (time.monotonic() - t) * 1e3
        self.sequence = ViewSequence(self.station, self.pipeline, self.book)

    def close(self) -> None:
        if self.pipeline is not None:
            self.pipeline.close()
        if self.capture is not None:
            self.capture.close()
        self.pipeline = self.capture = None

    def _open_cameras(self) -> None:
        scene = None
        if any(c.driver.kind == "sim" for c in self.station.cameras):
            from drivers.cameras import SimScene

            assert self.active is not None
            scene = SimScene(self.station, self.active.config,
                             np.random.default_rng(self.options.sim_seed), self.options.sim_render,
                             keep_poses=self.options.sim_keep_poses)
            if self.options.sim_part_at_reference:
                scene.set_part_pose(self.active.config.T_rf_from_pf0.matrix)
        self.scene = scene
        cams = [make_camera(c, scene) for c in self.station.cameras]
        self.capture = CaptureGroup(cams)
        down = {k: v for k, v in self.capture.wait_ready(self.options.camera_ready_s).items() if v}
        for cid, err in down.items():
            log.warning("camera %s not up at start (%s); it keeps reconnecting", cid, err)

    def note_append_ms(self, ms: float) -> None:
        """How long the record's append took (the pipeline keeps its deadline reserve)."""
        if self.pipeline is not None:
            self.pipeline.note_append_ms(ms)

    # ------------------------------------------------------------------ calibration
    def _active_calibration(self) -> tuple[int, Any] | None:
        """The store's active version of the calibration named after the station (seeded from
        the station file's ``calibration:`` at start-up, replaced by REST uploads): (version,
        CalibrationFile), or None when the station has none."""
        from mvpose_core.calibration.files import CalibrationFile
        from server.errors import NotFoundError

        assert self.services is not None
        try:
            info, content = self.services.store.versions.content("calibration",
                                                                 self.file_station.name)
        except NotFoundError:
            return None
        return info.version, CalibrationFile.model_validate(content)

    def active_calibration(self) -> tuple[int, Any] | None:
        """(version, CalibrationFile) of the store's active calibration, None without one.
        Blocking: it reads the store."""
        return self._active_calibration()

    def _apply_calibration(self) -> tuple[str, str] | None:
        """Put the active calibration into the station model (from the station file's model,
        so one calibration never stacks on another)."""
        from mvpose_core.calibration.files import apply_calibration

        active = self._active_calibration()
        self.calibration_version = active[0] if active else None
        if active is None:
            self.station = self.file_station
            return None
        version, calib = active
        self.station = apply_calibration(self.file_station, calib)
        log.info("station %s: calibration %s (sha256 %s), version %d", self.station.name,
                 calib.id, calib.sha256[:12], version)
        return calib.id, calib.sha256

    def _reload_calibration(self) -> bool:
        """On the trigger thread: a calibration version activated through the API is measured
        with from the next trigger on (the pipeline is built again and warmed up)."""
        assert self.capture is not None and self.book is not None
        active = self._active_calibration()
        if (active[0] if active else None) == self.calibration_version:
            return False
        calib = self._apply_calibration()
        old = self.pipeline
        pipeline = Pipeline(self.station, self.capture, options=self.options.pipeline)
        for recipe in self.book.recipes.values():
            with contextlib.suppress(Exception):  # two passes: a trigger may be waiting
                pipeline.warm_up(recipe.config, passes=2)
        self.pipeline = pipeline
        self.sequence = ViewSequence(self.station, pipeline, self.book)
        assert self.provenance is not None
        self.provenance = replace(self.provenance, calibration=calib)
        if old is not None:
            old.close()
        return True

    # ------------------------------------------------------------------ recipes
    @property
    def active(self) -> ActiveRecipe | None:
        """The selected recipe."""
        return self.book.selected if self.book else None

    def any_recipe(self) -> ActiveRecipe:
        """The selected recipe, else the first (what a refused trigger's record names)."""
        assert self.book is not None
        return self.book.selected or next(iter(self.book.recipes.values()))

    def versions_changed(self) -> bool:
        """Off the trigger thread (a database read, which a frozen database holds): whether a
        recipe or calibration version was activated elsewhere since the last reload."""
        assert self.book is not None and self.services is not None
        versions = self.services.store.versions
        recipes = {s.name: s.active_version for s in versions.names("recipe")}
        if any(recipes.get(n) != r.version for n, r in self.book.recipes.items()):
            return True
        calibrations = {s.name: s.active_version for s in versions.names("calibration")}
        return calibrations.get(self.file_station.name) != self.calibration_version

    def reload_versions(self) -> bool:
        """On the trigger thread: recipe and calibration versions activated elsewhere; True
        when something changed."""
        assert self.book is not None
        before = {n: r.version for n, r in self.book.recipes.items()}
        self.book.reload_if_changed()
        calibrated = self._reload_calibration()
        return calibrated or before != {n: r.version for n, r in self.book.recipes.items()}

    def select(self, name: str, version: int | None, by: str) -> ActiveRecipe:
        """On the trigger thread: select recipe ``name`` (activating ``version`` first)."""
        assert self.book is not None and self.sequence is not None
        self.sequence.clear()
        return self.book.select(name, version, by)

    def unselect(self) -> None:
        """On the trigger thread: no recipe is selected any more."""
        assert self.book is not None and self.sequence is not None
        self.sequence.clear()
        self.book.selected = None

    def clear_sequence(self) -> None:
        """Drop a half-done multi-view sequence."""
        if self.sequence is not None:
            self.sequence.clear()

    def teach_from_measurement(self, measurement_id: int, by: str) -> ActiveRecipe:
        """On the trigger thread: the stored measurement becomes the selected recipe's
        reference."""
        assert self.book is not None
        return self.book.teach_from_measurement(measurement_id, by)

    def teach_if_armed(self, recipe: ActiveRecipe, rec: MeasurementRecord,
                       result_id: int) -> bool:
        """On the trigger thread: an armed teach takes this final OK result as the recipe's
        reference; True if it did."""
        if self.teach_armed_by is None or rec.result != "OK" or rec.T_rf_from_pf is None:
            return False
        assert self.book is not None
        by, self.teach_armed_by = self.teach_armed_by, None
        self.book.teach(recipe.config.name, np.array(rec.T_rf_from_pf), by,
                        f"taught by {by} from trigger {rec.trigger_id} (result {result_id})")
        return True
