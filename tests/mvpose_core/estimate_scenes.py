"""Shared synthetic scenes for the estimator tests: example stations, noiseless truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mvpose_core.estimate import Observation
from mvpose_core.scene import ViewCamera, view_cameras
from mvpose_core.station import RecipeConfig, StationConfig, load_station
from mvpose_core.synth import synthetic_observations

STATIONS = Path(__file__).resolve().parents[2] / "deploy" / "stations"
NAMES = ["lab", "station1", "station2"]


def station(
    name: str,
) -> tuple[StationConfig, RecipeConfig, list[ViewCamera], dict[str, np.ndarray]]:
    st = load_station(STATIONS / f"{name}.yaml")
    rec = st.recipe()
    marks = {m.id: np.asarray(m.position, dtype=float) for m in rec.marks}
    return st, rec, view_cameras(st), marks


def noiseless(
    name: str, T_rf_from_pf: np.ndarray | None = None
) -> tuple[list[Observation], list[ViewCamera], dict[str, np.ndarray], np.ndarray]:
    st, rec, cams, marks = station(name)
    T = rec.T_rf_from_pf0.matrix if T_rf_from_pf is None else T_rf_from_pf
    obs = synthetic_observations(st, rec, T, np.random.default_rng(0), 0.0, require_in_image=False)
    return obs, cams, marks, T
