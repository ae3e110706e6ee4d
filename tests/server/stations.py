"""Station files and settings for the pipeline and end-to-end tests (deploy/stations variants)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from drivers.cameras import RenderOptions
from server.settings import Settings
from server.station.core import StationOptions

ROOT = Path(__file__).resolve().parents[2]
STATIONS = ROOT / "deploy" / "stations"
ENGINEER = "mvp_engineer-token-for-the-pipeline-tests-0000000"

# Rendering 4 MP frames is the main cost of these tests: no shot noise and 4x4 instead of 16x16
# super-sampling at the mark rims. Detection and the estimate still see anti-aliased, blurred,
# unevenly lit marks. The read noise is each simulated camera's own (the station file's
# ``driver.image_noise``, 2 grey levels by default, which the scene puts over this
# ``noise_sigma``): a test that needs none takes the station file edit :func:`no_read_noise`.
FAST_RENDER = RenderOptions(noise_sigma=0.0, shot_noise_gain=0.0, supersample=4)


def relaxed_deadline(data: dict[str, Any]) -> None:
    """Correctness tests run on a shared, loaded 2-core machine: a 50 ms deadline would turn
    scheduler hiccups into NOK results. The deadline has its own test (test_pipeline.py) and
    the latency is measured by bench/bench_station.py."""
    data["deadline_ms"] = 1000.0


def no_read_noise(data: dict[str, Any]) -> None:
    """Simulated cameras without read noise: a full-frame normal draw per camera, two thirds of
    a 4 MP rendering's time at :data:`FAST_RENDER` (station 1: 0.28 -> 0.10 s per part move
    of its four cameras). For tests that make many moves and judge the answers against the
    tolerances, not the detector's noise."""
    for cam in data["cameras"]:
        if cam["driver"]["kind"] == "sim":
            cam["driver"]["image_noise"] = 0.0


def station_file(tmp: Path, name: str, *edits: Callable[[dict[str, Any]], None]) -> Path:
    """A copy of deploy/stations/<name>.yaml in ``tmp``, changed by ``edits``."""
    data = yaml.safe_load((STATIONS / f"{name}.yaml").read_text())
    # The tests' PLC twin beats on the test's own event loop, beside the test's blocking calls
    # (wait_idle, store reads): on a busy machine a beat can come later than the product's 1 s
    # default, and the station would go to ERROR (WATCHDOG) under the test. The watchdog itself
    # is tested in tests/drivers/test_plc_server.py.
    data.setdefault("links", {}).setdefault("modbus", {}).setdefault("watchdog_s", 10.0)
    for edit in edits:
        edit(data)
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def settings_for(station: Path, data_dir: Path, database_url: str | None = None) -> Settings:
    return Settings(station=station, data_dir=data_dir, database_url=database_url,
                    bootstrap_token=ENGINEER, images_ok_every=1000)


def runtime_options(seed: int = 0) -> StationOptions:
    return StationOptions(sim_seed=seed, sim_render=FAST_RENDER)
