"""The per-trigger pipeline through the real runtime: deadline, camera faults, views, teach, REST.

Every test runs the production wiring (app lifespan, store, runtime, Modbus server on a free port)
with station 1's simulated cameras and talks to it as the PLC does, through the PLC twin.
"""

from __future__ import annotations

import asyncio
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from stations import ENGINEER, relaxed_deadline, runtime_options, settings_for, station_file

from drivers.links.layout import Command, Status
from mvpose_core.reasons import Reason
from mvpose_core.synth import displaced, random_displacement
from server.loopback import move_part, running_station, trigger
from server.pipeline import PipelineOptions, _usual_slow, auto_detect_processes

pytestmark = pytest.mark.timeout(120)


def _at(recipe: Any, rng: np.random.Generator) -> np.ndarray:
    return recipe.T_rf_from_pf0.matrix @ random_displacement(rng, 15.0, 1.5)


async def test_past_the_deadline_the_plc_gets_an_error_code_never_an_offset(tmp_path: Path) -> None:
    def tight(d: dict[str, Any]) -> None:
        d["deadline_ms"] = 2.0  # less than any capture + detection of four 4 MP frames

    settings = settings_for(station_file(tmp_path, "station1", tight), tmp_path / "var")
    # the capture may take 500 × the 2 ms deadline: the cameras always answer, even on a busy
    # machine, and the result is late by its processing (a grab cut short would be CAMERA_FAILED)
    opts = replace(runtime_options(), pipeline=PipelineOptions(capture_share=500.0))
    async with running_station(settings, opts, http_port=None) as lb:
        recipe = lb.runtime.active.config
        T = _at(recipe, np.random.default_rng(1))
        await move_part(lb.runtime, lb.twin, T)
        status, row = await trigger(lb.twin, recipe, 41, T)
        assert status.has(Status.RESULT_VALID) and not status.has(Status.RESULT_OK)
        assert status.result_code == Reason.DEADLINE_EXCEEDED
        assert status.offset_float == (0.0,) * 6
        lb.runtime.wait_idle()
        stored = lb.runtime.services.store.measurements.get(lb.runtime.last["measurement_id"])
        rec = stored.record
        # What the PLC got is what the audit trail says, with the pose kept for diagnosis.
        assert (rec.trigger_id, rec.result, rec.reason) == (41, "NOK", "DEADLINE_EXCEEDED")
        assert rec.T_rf_from_pf is not None and "deadline" in (rec.message or "")
        assert {"capture", "detect", "measure", "total"} <= set(rec.timings_ms)


async def test_a_camera_that_times_out_gives_camera_failed_and_the_others_still_measure(
    tmp_path: Path,
) -> None:
    def fault(d: dict[str, Any]) -> None:
        cam = next(c for c in d["cameras"] if c["id"] == "back_left")
        cam["driver"]["fault"] = {"kind": "timeout", "every_n": 1}

    station = station_file(tmp_path, "station1", fault, relaxed_deadline)
    settings = settings_for(station, tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        recipe = lb.runtime.active.config
        T = _at(recipe, np.random.default_rng(2))
        await move_part(lb.runtime, lb.twin, T)
        status, _ = await trigger(lb.twin, recipe, 7, T)
        assert status.result_code == Reason.CAMERA_FAILED
        lb.runtime.wait_idle()
        rec = lb.runtime.services.store.measurements.get(lb.runtime.last["measurement_id"]).record
        by_cam = {c.camera_id: c.detections for c in rec.detections}
        assert all(not d.found and "camera" in (d.reason or "") for d in by_cam["back_left"])
        assert all(d.found for cid in ("top_left", "top_right", "back_right")
                   for d in by_cam[cid])
        # The NOK frames are archived (after the PLC got its answer).
        assert rec.images and {i.camera_id for i in rec.images} == {
            "top_left", "top_right", "back_right"}


async def test_unknown_view_and_recipe_are_refused_and_recorded(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        recipe = lb.runtime.active.config
        T = _at(recipe, np.random.default_rng(3))
        await move_part(lb.runtime, lb.twin, T)
        status, _ = await trigger(lb.twin, recipe, 9, T, view_index=7, part_id="VIN-9")
        assert status.result_code == Reason.UNKNOWN_VIEW
        done = await lb.twin.command(Command.SELECT_RECIPE, 2)
        assert done.has(Status.COMMAND_FAILED)
        assert done.command_result == Reason.UNKNOWN_RECIPE
        lb.runtime.wait_idle()  # the record's database id is known once it is committed
        rec = lb.runtime.services.store.measurements.get(lb.runtime.last["measurement_id"]).record
        assert (rec.trigger_id, rec.part_id, rec.reason) == (9, "VIN-9", "UNKNOWN_VIEW")
        status, row = await trigger(lb.twin, recipe, 10, T)  # the station still measures
        assert status.result_code == 0 and row is not None
        assert row.trans_err_mm < recipe.tolerances.translation_mm


async def test_rest_trigger_teach_and_plc_teach_make_new_recipe_versions(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    rng = np.random.default_rng(4)
    async with running_station(settings, runtime_options()) as lb:
        recipe = lb.runtime.active.config
        tol = recipe.tolerances
        T = _at(recipe, rng)
        await move_part(lb.runtime, lb.twin, T)
        async with httpx.AsyncClient(base_url=lb.base_url + "/api/v1", timeout=20,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            made = await api.post("/tokens", json={"name": "mes", "role": "read"})
            assert made.status_code == 201, made.text
            read = {"Authorization": f"Bearer {made.json()['token']}"}
            refused = await api.post("/station/trigger", json={"part_id": "X"}, headers=read)
            assert refused.status_code == 403
            assert (await api.get("/station/status", headers=read)).status_code == 200

            answer = (await api.post("/station/trigger", json={"part_id": "COMM-1"})).json()
            assert answer["result_code"] == 0, answer
            assert answer["record"]["trigger_id"] == 0 and answer["record"]["part_id"] == "COMM-1"
            assert np.abs(answer["offset"][:3]).max() > 1.0  # the part is displaced
            event = answer["event"]  # the result event, every field of it
            assert event["result_id"] == answer["result_id"]
            assert event["residual_rms_px"] == answer["record"]["residuals"]["rms_px"] > 0
            assert (event["part_id"], event["offset"], event["length_unit"]) == (
                "COMM-1", answer["offset"], "mm")

            mid = answer["measurement_id"]
            taught = await api.post("/station/teach", json={"measurement_id": mid})
            assert taught.status_code == 200, taught.text
            assert taught.json()["version"] == 2
            again = (await api.post("/station/trigger", json={"part_id": "COMM-2"})).json()
            assert again["record"]["recipe_version"] == 2
            # Same part, same place, new reference: the offset is zero within the noise.
            assert np.abs(again["offset"][:3]).max() < tol.translation_mm / 2
            assert np.abs(again["offset"][3:]).max() < tol.rotation_deg / 2

            bad = await api.post("/station/teach", json={"measurement_id": 10**6})
            assert bad.status_code == 404

            # By PLC command: armed now, taken from the next final OK result.
            T2 = _at(recipe, rng)
            await move_part(lb.runtime, lb.twin, T2)
            done = await lb.twin.command(Command.TEACH_REFERENCE)
            assert done.has(Status.COMMAND_DONE)
            status, _ = await trigger(lb.twin, recipe, 21, T2)
            assert status.result_code == 0
            status, _ = await trigger(lb.twin, recipe, 22, T2)
            assert np.abs(status.offset_float[:3]).max() < tol.translation_mm / 2
            versions = (await api.get("/recipes/floor_panel/versions")).json()
            assert [v["version"] for v in versions] == [1, 2, 3]
            assert versions[-1]["active"] and versions[-1]["created_by"] == "plc"
            state = (await api.get("/station/status")).json()
            assert state["recipe"]["version"] == 3
            assert state["last_result"]["trigger_id"] == 22
            assert state["cameras"] and all(s.startswith("up") for s in state["cameras"].values())
            assert state["plc"]["plc_online"] and state["plc"]["watchdog_trips"] == 0
            beat = state["plc"]["server_heartbeat"]
            deadline = time.monotonic() + 5
            while (await api.get("/station/status")).json()["plc"]["server_heartbeat"] == beat:
                assert time.monotonic() < deadline, "the server heartbeat does not change"
                await asyncio.sleep(0.02)


async def test_the_station_calibration_is_applied_and_recorded(tmp_path: Path) -> None:
    from mvpose_core.calibration.files import (
        CalibrationFileError,
        CameraCalibration,
        InputsSummary,
        make_calibration,
        save_calibration,
    )
    from mvpose_core.station import load_station

    base = load_station(station_file(tmp_path, "station1"))
    cam = base.camera("top_left").model
    calibrated = CameraCalibration(  # the camera as the calibration measured it: fx 1 px more
        intrinsics={"fx": cam.fx + 1.0, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy},
        distortion=list(cam.dist), image_size=(cam.width, cam.height))
    calib = make_calibration("intrinsics", InputsSummary(board="test"),
                             cameras={"top_left": calibrated}, station="station1")
    save_calibration(tmp_path / "calib.json", calib)

    def use(d: dict[str, Any]) -> None:
        d["calibration"] = "calib.json"  # relative to the station file

    settings = settings_for(station_file(tmp_path, "station1", use, relaxed_deadline),
                            tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        assert lb.runtime.station.camera("top_left").intrinsics.fx == cam.fx + 1.0
        recipe = lb.runtime.active.config
        T = _at(recipe, np.random.default_rng(6))
        await move_part(lb.runtime, lb.twin, T)
        status, row = await trigger(lb.twin, recipe, 3, T)
        assert status.result_code == 0 and row is not None
        lb.runtime.wait_idle()
        rec = lb.runtime.services.store.measurements.get(lb.runtime.last["measurement_id"]).record
        assert (rec.calibration_id, rec.calibration_hash) == (calib.id, calib.sha256)

    (tmp_path / "calib.json").write_text((tmp_path / "calib.json").read_text().replace(
        '"fx": ', '"fx": 1', 1))  # tampered: the content hash no longer matches
    with pytest.raises(CalibrationFileError, match="calib.json: content hash"):
        async with running_station(settings, runtime_options(), http_port=0):
            pass


# A detection worker detects one image alone, at up to 2.65x the CPU of the images together on
# the trigger thread (python -m bench.detect_alone): fewer than four workers would make a
# displaced part slower than the trigger thread, so `mvpose serve` starts none below 8 cores.
@pytest.mark.parametrize(("cores", "workers"), [(None, 0), (1, 0), (2, 0), (4, 0), (7, 0),
                                                (8, 4), (16, 4), (64, 4)])
def test_detection_processes_start_only_where_four_of_them_fit(
    monkeypatch: pytest.MonkeyPatch, cores: int | None, workers: int
) -> None:
    monkeypatch.setattr("os.cpu_count", lambda: cores)
    assert auto_detect_processes() == workers


@pytest.mark.parametrize("where", ["processes", "threads"])
async def test_detection_in_workers_matches_detection_in_process(
    tmp_path: Path, where: str
) -> None:
    """Detection on worker processes or on detection threads (the default is the trigger
    thread) gives what one image detected alone gives."""
    from multiprocessing import shared_memory

    from mvpose_core.detect import detect_marks
    from server.station.core import StationOptions

    opts = (PipelineOptions(detect_processes=2) if where == "processes"
            else PipelineOptions(detect_workers=2))
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    rt_opts = StationOptions(sim_seed=0, sim_render=runtime_options().sim_render, pipeline=opts)
    async with running_station(settings, rt_opts, http_port=None) as lb:
        rt = lb.runtime
        recipe = rt.active.config
        T = _at(recipe, np.random.default_rng(8))
        await move_part(rt, lb.twin, T)
        status, row = await trigger(lb.twin, recipe, 5, T)
        assert status.result_code == 0 and row is not None
        assert row.trans_err_mm < recipe.tolerances.translation_mm
        rt.wait_idle()  # the record is in the database (its id is known once it is committed)
        rec = rt.services.store.measurements.get(rt.last["measurement_id"]).record
        blocks: list[str] = []
        if where == "processes":
            assert rt.pipeline._pool is None
            blocks = [b.name for b in rt.pipeline._procs._blocks.values()]
            assert len(blocks) == 4
            # Each (camera, recipe) pair went to the workers pickled once, under one token; the
            # next trigger reuses them (the workers keep the objects, so their caches hit).
            tokens = sorted(token for token, _ in rt.pipeline._procs._sent.values())
            assert len(tokens) == 4
            status, _ = await trigger(lb.twin, recipe, 6, T)
            assert status.result_code == 0
            assert sorted(token for token, _ in rt.pipeline._procs._sent.values()) == tokens
        else:
            assert rt.pipeline._procs is None and rt.pipeline._pool is not None
        cams = rt.pipeline.view_cameras(1, None)
        for cd in rec.detections:
            here = detect_marks(rt.scene.frame(cd.camera_id), cams[cd.camera_id], recipe,
                                recipe.T_rf_from_pf0.matrix, opts.detect)
            from mvpose_core.detect import correct_centres

            here = correct_centres(here, cams[cd.camera_id], recipe,
                                   np.array(rec.T_rf_from_pf))
            got = {d.mark_id: d.uv for d in cd.detections}
            for d in here:
                # Corrected at the prior pose, or (second pass) at the final pose's predecessor:
                # within the re-correction threshold of the correction at the final pose.
                assert np.hypot(*(np.array(got[d.mark_id]) - d.uv)) <= opts.recorrect_px + 1e-3
    for name in blocks:  # the shared-memory blocks are gone with the runtime
        with pytest.raises(FileNotFoundError):
            shared_memory.SharedMemory(name=name)


async def test_start_up_warms_the_pipeline_without_recording_anything(tmp_path: Path) -> None:
    """The runtime runs detection and measurement once on blank frames and the recipe's own
    projections before it takes triggers: nothing of that is stored, and the first trigger
    measures as any other."""
    from server.store.schemas import MeasurementFilter

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        rt = lb.runtime
        recipe = rt.active.config
        assert set(rt.warmed_ms) == set(rt.book.recipes) and rt.warmed_ms[recipe.name] > 0
        assert rt.status()["warm_up_ms"] == {k: round(v, 1) for k, v in rt.warmed_ms.items()}
        assert rt.services.store.measurements.count(MeasurementFilter()) == 0
        T = _at(recipe, np.random.default_rng(5))
        await move_part(rt, lb.twin, T)
        status, _ = await trigger(lb.twin, recipe, 1, T)
        assert status.result_code == 0
        rt.wait_idle()
        assert rt.services.store.measurements.count(MeasurementFilter()) == 1


def test_the_store_reserve_is_the_p90_of_recent_writes_without_the_slowest() -> None:
    """The deadline's store reserve: p90 of recent write times (as np.percentile) without the
    slowest one, so one stall never counts."""
    rng = np.random.default_rng(4)
    assert _usual_slow([]) == 0.0
    assert _usual_slow([60.0]) == 0.0
    assert _usual_slow([2.0, 60.0]) == 2.0
    for n in (3, 5, 50):
        times = list(rng.exponential(2.0, n))
        rest = sorted(times)[:-1]
        assert _usual_slow(times) == pytest.approx(float(np.percentile(rest, 90)), abs=1e-12)


async def test_one_slow_store_write_does_not_fail_the_next_trigger_two_do(tmp_path: Path) -> None:
    """A single fsync stall (here 10 s, as told to the pipeline) keeps nothing in reserve; a
    second one does, and the next trigger is answered DEADLINE_EXCEEDED before its offset."""
    def deadline(d: dict[str, Any]) -> None:
        # far above a trigger's work on a busy machine, far below the stalls
        d["deadline_ms"] = 2000.0

    settings = settings_for(station_file(tmp_path, "station1", deadline), tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        recipe = lb.runtime.active.config
        rng = np.random.default_rng(8)
        codes = []
        for trigger_id in (1, 2, 3):
            if trigger_id > 1:
                lb.runtime.pipeline.note_append_ms(10000.0)
            T = _at(recipe, rng)
            await move_part(lb.runtime, lb.twin, T)
            status, _ = await trigger(lb.twin, recipe, trigger_id, T)
            lb.runtime.wait_idle()
            codes.append(status.result_code)
        assert codes == [0, 0, Reason.DEADLINE_EXCEEDED], codes
        rec = lb.runtime.services.store.measurements.get(lb.runtime.last["measurement_id"]).record
        assert rec.reason == "DEADLINE_EXCEEDED" and "to be stored" in (rec.message or "")


async def test_a_calibration_activated_over_rest_is_measured_with_and_recorded(
    tmp_path: Path,
) -> None:
    from mvpose_core.calibration.files import CameraCalibration, InputsSummary, make_calibration

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    async with running_station(settings, runtime_options()) as lb:
        assert lb.runtime.status()["calibration"] is None  # the station file names none
        cam = lb.runtime.station.camera("top_left").model
        calib = make_calibration("intrinsics", InputsSummary(board="test"), station="station1",
                                 cameras={"top_left": CameraCalibration(
                                     intrinsics={"fx": cam.fx + 2.0, "fy": cam.fy,
                                                 "cx": cam.cx, "cy": cam.cy},
                                     distortion=list(cam.dist),
                                     image_size=(cam.width, cam.height))})
        async with httpx.AsyncClient(base_url=lb.base_url + "/api/v1", timeout=20,
                                     headers={"Authorization": f"Bearer {ENGINEER}"}) as api:
            r = await api.post("/calibrations/station1/versions",
                               json={"content": calib.model_dump(mode="json"), "activate": True})
            assert r.status_code == 201, r.text
            # Activation goes to the station at once: the next trigger measures with it.
            assert lb.runtime.station.camera("top_left").intrinsics.fx == cam.fx + 2.0
            state = (await api.get("/station/status")).json()
            assert state["calibration"] == {"id": calib.id, "sha256": calib.sha256, "version": 1}
        recipe = lb.runtime.active.config
        T = _at(recipe, np.random.default_rng(9))
        await move_part(lb.runtime, lb.twin, T)
        status, _ = await trigger(lb.twin, recipe, 7, T)
        lb.runtime.wait_idle()
        rec = lb.runtime.services.store.measurements.get(lb.runtime.last["measurement_id"]).record
        assert (rec.calibration_id, rec.calibration_hash) == (calib.id, calib.sha256)
        assert rec.reason_code == status.result_code


# After two parts in a row at one place the station searches its first windows where the last
# good part was (mvpose_core.detect.follow.next_near). That memory never keeps a part from
# being found: a part far from the reference, one a little beside it, one back at the
# reference, one at the opposite side of the tolerance and one there again are each measured OK
# at their own pose, on the trigger thread and on detection processes.
@pytest.mark.parametrize("processes", [0, 2])
async def test_each_part_is_measured_wherever_the_last_one_was(
    tmp_path: Path, processes: int
) -> None:
    from server.station.core import StationOptions

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline), tmp_path / "var")
    opts = StationOptions(sim_seed=0, sim_render=runtime_options().sim_render,
                          pipeline=PipelineOptions(detect_processes=processes))
    async with running_station(settings, opts, http_port=None) as lb:
        recipe = lb.runtime.active.config
        for n, share in enumerate((0.6, 0.63, 0.0, -0.8, -0.8)):
            T = displaced(recipe, share)
            await move_part(lb.runtime, lb.twin, T)
            status, row = await trigger(lb.twin, recipe, 60 + n, T)
            assert row is not None and status.has(Status.RESULT_OK), (share, status.result_code)
            assert row.rot_err_deg < 0.02 and row.trans_err_mm < 0.2, (share, row)
