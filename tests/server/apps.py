"""Settings and records shared by the API tests: a station-1 app on SQLite in a temp dir."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import anyio.to_thread
import numpy as np
from records import make_record

from mvpose_core.reasons import Reason
from server.settings import Settings
from server.state import Services
from server.store.schemas import StoredMeasurement

ROOT = Path(__file__).resolve().parents[2]
STATION1 = ROOT / "deploy" / "stations" / "station1.yaml"
ENGINEER = "mvp_engineer-secret-for-tests-0123456789"


def settings(tmp_path: Path, **kw: Any) -> Settings:
    base: dict[str, Any] = {"data_dir": tmp_path / "var", "station": STATION1,
                            "bootstrap_token": ENGINEER, "software_version": "0.1.0-test"}
    return Settings(**(base | kw))


async def record_some(services: Services, reasons: list[Reason], seed: int = 0,
                      **kw: Any) -> list[StoredMeasurement]:
    """Store one record per reason, as the pipeline does (from a worker thread)."""
    rng = np.random.default_rng(seed)
    out = []
    for i, reason in enumerate(reasons, start=1):
        rec = make_record(rng, services.station_name, trigger_id=i, reason=reason, **kw)
        out.append(await anyio.to_thread.run_sync(services.record_measurement, rec))
    return out
