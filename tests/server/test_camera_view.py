"""The live camera view on the station: frames with focus and light figures over the control
channel, at most one set per period, never in a trigger's way (real station, simulated cameras).
"""

from __future__ import annotations

import asyncio
import base64
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from stations import relaxed_deadline, runtime_options, settings_for, station_file
from waiting import until_sync

from server.loopback import running_server
from server.station.camera_view import PERIOD_S
from server.station.client import StationClient


def slow_cameras(data: dict[str, Any]) -> None:
    """Cameras whose exposure and transfer take 150 ms: a preview is in flight long enough
    for a trigger to come during it."""
    relaxed_deadline(data)
    for cam in data["cameras"]:
        cam.setdefault("driver", {})["latency_ms"] = 150.0


async def test_frames_figures_and_the_rate(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    opts = replace(runtime_options(), sim_part_at_reference=True)
    async with running_server(settings, opts, http_port=None):
        client = StationClient(settings.resolved_control_socket, status_max_age_s=0.0)

        def run() -> None:
            first = client.camera_view(640)
            assert first.seq == 1 and first.period_s == PERIOD_S and first.note == ""
            for cam in first.cameras:
                assert cam.jpeg_base64 is not None, cam.note
                image = cv2.imdecode(np.frombuffer(base64.b64decode(cam.jpeg_base64), np.uint8),
                                     cv2.IMREAD_GRAYSCALE)
                assert image.shape == (cam.height, cam.width) and 320 < cam.width <= 640
                assert cam.focus is not None and cam.focus > 0
                assert cam.focus_area == "mark windows"  # the recipe's marks in this camera
                assert cam.mean is not None and 0 < cam.mean < 255
                assert cam.saturated_pct is not None and cam.dark_pct is not None
            # asked again at once: the same set (at most one grab per period, however many ask)
            again = client.camera_view(640)
            grabs = client.status().part("camera_view")
            assert grabs is not None
            if again.seq == first.seq:
                assert again == first
            assert grabs["grabs"] <= 2 and grabs["requests"] == 2

        await asyncio.to_thread(run)


async def test_a_trigger_during_a_preview_is_answered_with_its_own_frames(
        tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", slow_cameras), tmp_path / "var")
    opts = replace(runtime_options(), sim_part_at_reference=True)
    async with running_server(settings, opts, http_port=None) as rs:
        rt = rs.runtime
        client = StationClient(settings.resolved_control_socket, status_max_age_s=0.0)

        def run() -> None:
            # A trigger must come while the preview waits for its frames (150 ms): on a busy
            # machine it may come late, so the pair is tried again until one came in time.
            for k in range(20):
                out: list[Any] = []
                viewer = threading.Thread(
                    target=lambda out=out: out.append(client.camera_view(320)))
                viewer.start()
                until_sync(lambda out=out: rt.camera_view.grabbing or out, "a preview in flight")
                answer = client.trigger(part_id=f"VIN-{k}", trigger_id=100 + k)
                viewer.join(30)
                # the trigger is answered normally, with its own result
                assert answer.result_code == 0 and answer.final, answer.message
                assert answer.record is not None and answer.offset is not None
                if rt.camera_view.counts["preempted"]:
                    break
                t_done = time.monotonic()  # the station grabs again a period later
                until_sync(lambda t=t_done: time.monotonic() - t >= PERIOD_S, "the next period")
            counts = rt.camera_view.counts
            assert counts["preempted"] >= 1, counts  # a camera's preview gave way
            view = out[0]
            assert any("gave way to a trigger" in c.note or "trigger came first" in c.note
                       for c in view.cameras), view

        await asyncio.to_thread(run)
        assert rt.camera_view.counts["requests"] >= 1


async def test_nothing_is_grabbed_when_nobody_asks(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    async with running_server(settings, runtime_options(), http_port=None) as rs:
        client = StationClient(settings.resolved_control_socket, status_max_age_s=0.0)

        def run() -> None:
            client.trigger(part_id="VIN-1", trigger_id=1)
            part = client.status().part("camera_view")
            assert part is not None and part["grabs"] == 0 and part["requests"] == 0

        await asyncio.to_thread(run)
        assert rs.runtime.camera_view.counts["grabs"] == 0
