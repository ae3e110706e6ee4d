"""The station's recipes as the runtime uses them: active stored versions, selection, teaching.

A recipe's content lives in the store as versions (server/store/versions.py); the station file
seeds them at start-up. Teaching the reference pose from a measurement is one more version —
content with the new ``T_rf_from_pf0``, its sha256, time, author and a comment naming the
measurement — activated at once, like a calibration. The PLC selects recipes by number: their
1-based position in the station file.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import numpy as np

from mvpose_core.station import Pose, RecipeConfig, StationConfig
from mvpose_core.transforms import Array
from server.state import recipe_content
from server.store import Store

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ActiveRecipe:
    """A recipe as the station uses it now: its content (taught reference included) and version."""

    config: RecipeConfig
    version: int  # the store's version number (goes into every record)
    sha256: str
    number: int  # what the PLC selects it by: 1-based position in the station file


class RecipeBook:
    """The active version of every recipe of the station, and which one is selected."""

    def __init__(self, station: StationConfig, store: Store) -> None:
        self.station = station
        self.store = store
        self._lock = threading.Lock()  # REST threads read while the trigger thread reloads
        self.recipes: dict[str, ActiveRecipe] = {}
        self.selected: ActiveRecipe | None = None
        self.load()

    def load(self) -> None:
        """Read the active stored version of every recipe of the station file."""
        recipes = {}
        for number, rc in enumerate(self.station.recipes, start=1):
            info, content = self.store.versions.content("recipe", rc.name)
            cfg = RecipeConfig.model_validate({**content, "version": info.version})
            recipes[rc.name] = ActiveRecipe(cfg, info.version, info.sha256, number)
        with self._lock:
            current = self.selected.config.name if self.selected else self.station.recipe().name
            self.recipes = recipes
            self.selected = recipes[current]

    def reload_if_changed(self) -> None:
        """Pick up versions activated elsewhere (REST: /recipes/{name}/versions/{v}/activate)."""
        active = {s.name: s.active_version for s in self.store.versions.names("recipe")}
        if any(active.get(n) != r.version for n, r in self.recipes.items()):
            self.load()

    def by_number(self, number: int) -> ActiveRecipe | None:
        return next((r for r in self.recipes.values() if r.number == number), None)

    def select(self, name: str, version: int | None = None, by: str = "plc") -> ActiveRecipe:
        """Select ``name``; with ``version``, activate that stored version first."""
        if name not in self.recipes:
            raise KeyError(f"station {self.station.name!r} has no recipe {name!r}")
        if version is not None:
            self.store.versions.activate("recipe", name, version, by)
            self.load()
        with self._lock:
            self.selected = self.recipes[name]
            return self.selected

    def teach(self, recipe: str, T_rf_from_pf: Array, by: str, comment: str) -> ActiveRecipe:
        """Store ``T_rf_from_pf`` as the recipe's new reference (zero offset): a new version."""
        current = self.recipes[recipe].config
        new = current.model_copy(update={"T_rf_from_pf0": Pose.from_matrix(T_rf_from_pf)})
        content = recipe_content(RecipeConfig.model_validate(new.model_dump()))
        info = self.store.versions.add("recipe", recipe, content, by, comment=comment)
        self.store.versions.activate("recipe", recipe, info.version, by)
        self.load()
        log.info("recipe %s: reference taught (%s), version %d", recipe, comment, info.version)
        return self.recipes[recipe]

    def teach_from_measurement(self, measurement_id: int, by: str) -> ActiveRecipe:
        """Teach from a stored OK measurement's pose."""
        stored = self.store.measurements.get(measurement_id)
        rec = stored.record
        if rec.result != "OK" or rec.T_rf_from_pf is None:
            raise ValueError(f"measurement {measurement_id} is {rec.result} ({rec.reason}): "
                             "only an OK measurement can be taught")
        if rec.recipe not in self.recipes:
            raise KeyError(f"measurement {measurement_id} is of unknown recipe {rec.recipe!r}")
        return self.teach(rec.recipe, np.array(rec.T_rf_from_pf), by,
                          f"taught from measurement {measurement_id} (seq {stored.seq})")
