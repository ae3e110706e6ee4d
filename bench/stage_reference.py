"""The station's trigger work alone, in the benchmark's own process: the reference for each stage.

The same station file, simulated scene (seed, pose), pipeline options, record builder and
durable writer (SQLite, synchronous=FULL, its own data directory) as the station process, driven
from one thread with nothing else running: no links, no control channel, no other process
talking to it. Each stage's time here, next to the same stage in the station process's records,
says how much the server itself costs (its threads, the Modbus polls, the API next door).
:class:`AloneOnThread` runs it on a thread of its own under the station's trigger priority
(SCHED_FIFO, ``MVPOSE_TRIGGER_PRIORITY``), as the station process runs its trigger path: on a
shared machine a reference at the normal priority would wait for other tasks the station does
not wait for.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from drivers.cameras import CaptureGroup, SimScene, make_camera
from drivers.links import LinkRequest
from mvpose_core.station import load_station
from server.pipeline import Pipeline, PipelineOptions
from server.recipes import RecipeBook
from server.settings import Settings
from server.state import open_services
from server.station import scheduling
from server.station.core import WriterSink
from server.station.records import Provenance, result_record
from server.station.sequence import ViewSequence

STAGES = ("capture", "detect", "measure", "correct", "append", "total")


class AloneStation:
    """The trigger thread's work (capture → record appended) without the station around it."""

    def __init__(self, station_file: Path, data_dir: Path, keep_poses: int = 0) -> None:
        self.services = open_services(Settings(station=station_file, data_dir=data_dir),
                                      bootstrap=False)
        station = load_station(station_file)
        self.station = station
        self.book = RecipeBook(station, self.services.store)
        recipe = self.book.selected
        assert recipe is not None
        # as the station process builds it (StationOptions(): seed 0, default rendering, the
        # part at the reference pose; the renderings of ``keep_poses`` recent poses kept)
        self.scene = SimScene(station, recipe.config, np.random.default_rng(0), None,
                              keep_poses=keep_poses)
        self.scene.set_part_pose(recipe.config.T_rf_from_pf0.matrix)
        self.capture = CaptureGroup([make_camera(c, self.scene) for c in station.cameras])
        self.capture.wait_ready(30)
        self.pipeline = Pipeline(station, self.capture, PipelineOptions())
        self.pipeline.warm_up(recipe.config)
        self.sequence = ViewSequence(station, self.pipeline, self.book)
        self.sink = WriterSink(self.services)
        self.prov = Provenance(station.name, self.services.software_version, None)
        self.next_id = 1

    def trigger(self) -> dict[str, float]:
        """One trigger: the stages' times (ms) as the record has them, plus the append."""
        t0 = time.monotonic()
        at = datetime.now(UTC)
        req = LinkRequest(link="bench", trigger_id=self.next_id, view_index=0, robot_pose=None,
                          part_id="", recipe=0)
        self.next_id += 1
        step = self.sequence.run(req, t0)
        assert step.result is not None, step.refused
        rec = result_record(self.prov, step.result, trigger_id=req.trigger_id, part_id=None,
                            triggered_at=at, recipe=step.recipe)
        t = time.monotonic()
        self.sink.append(rec)
        append = (time.monotonic() - t) * 1e3
        self.pipeline.note_append_ms(append)
        out = dict(step.result.timings_ms)
        out["append"] = append
        out["processing"] = (time.monotonic() - t0) * 1e3
        out["ok"] = float(step.result.ok)
        return out

    def close(self) -> None:
        self.sink.close()
        self.pipeline.close()
        self.capture.close()
        self.services.close()


class AloneOnThread:
    """An :class:`AloneStation` built and driven on a thread of its own that runs under the
    station's trigger priority (its camera and writer threads inherit it)."""

    def __init__(self, station_file: Path, data_dir: Path, keep_poses: int = 0) -> None:
        priority = int(os.environ.get("MVPOSE_TRIGGER_PRIORITY", scheduling.DEFAULT_PRIORITY))
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="alone",
                                        initializer=scheduling.enter, initargs=(priority,))
        self.alone = self._pool.submit(AloneStation, station_file, data_dir, keep_poses).result()
        self.scene = self.alone.scene
        self.book = self.alone.book

    def trigger(self) -> dict[str, float]:
        return self._pool.submit(self.alone.trigger).result()

    def close(self) -> None:
        try:
            self._pool.submit(self.alone.close).result()
        finally:
            self._pool.shutdown()
