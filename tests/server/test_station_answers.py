"""Every answer a link gives has a record with the same code and id, whatever fails.

The station in-process (server.loopback: the station with its control channel and the API), a
PLC twin over Modbus/TCP on loopback, and for the database faults a real PostgreSQL 15 frozen
with SIGSTOP.
"""

from __future__ import annotations

import asyncio
import gc
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from stations import relaxed_deadline, runtime_options, settings_for, station_file
from test_store_faults import _signal_all

from mvpose_core.reasons import Reason
from server.loopback import move_part, running_server, running_station, trigger
from server.store.schemas import MeasurementFilter
from tests.drivers import profinet_peer
from tests.waiting import until

SLACK_S = 0.5  # what a loaded machine may add to a deadline; tells "at the deadline" from "hung"


def _records(lb: Any) -> list[Any]:
    return list(lb.runtime.services.store.measurements.iterate(MeasurementFilter()))


def _deadline_ms(ms: float) -> Any:
    def edit(data: dict[str, Any]) -> None:
        data["deadline_ms"] = ms
    return edit


async def test_a_stuck_trigger_is_answered_with_a_recorded_timeout(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", _deadline_ms(500.0)),
                            tmp_path / "var")
    opts = runtime_options()
    from dataclasses import replace

    opts = replace(opts, answer_margin_s=0.3)
    async with running_station(settings, opts, http_port=None) as lb:
        recipe = lb.runtime.active.config
        # A camera that hangs, a detector stuck in a loop: the trigger thread does not come back.
        release = threading.Event()
        lb.runtime.triggers.executor.submit(release.wait, 30)
        t = time.monotonic()
        status, _ = await trigger(lb.twin, recipe, 41, None, timeout=5.0)
        waited = time.monotonic() - t
        assert status.result_code == Reason.TIMEOUT
        assert waited < 3.0, f"answered after {waited:.2f} s"  # not the PLC's 5 s give-up
        # journalled before the answer; the database commit follows (the trigger thread is
        # stuck, so wait_idle cannot be used: wait for the writer alone)
        assert lb.runtime.sink.flush(10.0)
        recs = _records(lb)
        # The station's watchdog answered (at the deadline + 0.3 s), not the link's backstop.
        assert "the trigger thread is stuck" in (recs[0].record.message or "")
        assert [(r.seq, r.record.trigger_id, r.record.reason_code) for r in recs] == [
            (status.result_id, 41, int(Reason.TIMEOUT))]
        assert recs[0].record.pose_valid is False
        release.set()
        lb.runtime.wait_idle()
        # The late result of trigger 41 is never recorded: the record says what the PLC was told.
        assert [r.record.trigger_id for r in _records(lb)] == [41]
        status, _ = await trigger(lb.twin, recipe, 42, None)
        lb.runtime.wait_idle()
        last = _records(lb)[-1]  # the station works on: the next answer, its own record
        assert (last.seq, last.record.trigger_id, last.record.reason_code) == (
            recs[0].seq + 1, 42, status.result_code) == (status.result_id, 42, status.result_code)


async def test_a_record_the_journal_refuses_is_answered_store_failed(tmp_path: Path) -> None:
    """A measured result whose record cannot be made durable (here: the writer is closed, so
    the journal takes no more links) reaches the PLC as STORE_FAILED (107) with no offset, and
    the trigger thread answers the next trigger the same way."""
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        recipe = lb.runtime.active.config
        T = recipe.T_rf_from_pf0.matrix
        await move_part(lb.runtime, lb.twin, T)
        status, _ = await trigger(lb.twin, recipe, 1, T)
        assert status.result_code == 0
        lb.runtime.sink.writer.close()
        for trigger_id in (2, 3):
            status, _ = await trigger(lb.twin, recipe, trigger_id, T, timeout=5.0)
            assert status.result_code == Reason.STORE_FAILED, status
            assert status.offset_float == (0.0,) * 6
        assert [r.seq for r in _records(lb)] == [1]  # nothing half-stored


async def test_a_ready_station_keeps_its_start_up_heap_out_of_the_collector(
        tmp_path: Path) -> None:
    """Once ready, the station's start-up objects are in the collector's permanent generation
    (server/station/heap.py: a collection of them stalled a trigger by ~140 ms), triggers are
    answered as before, and a stopped station gives them back."""
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    gc.unfreeze()
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        assert gc.get_freeze_count() > 10_000
        recipe = lb.runtime.active.config
        T = recipe.T_rf_from_pf0.matrix
        await move_part(lb.runtime, lb.twin, T)
        status, _ = await trigger(lb.twin, recipe, 1, T)
        assert status.result_code == 0
    assert gc.get_freeze_count() == 0


async def test_result_ids_are_the_records_and_survive_a_restart(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    seen: list[tuple[int, int]] = []
    for round_ in range(2):
        async with running_station(settings, runtime_options(), http_port=None) as lb:
            recipe = lb.runtime.active.config
            await move_part(lb.runtime, lb.twin, recipe.T_rf_from_pf0.matrix)
            for k in range(3):
                status, _ = await trigger(lb.twin, recipe, 100 * round_ + k, None)
                assert status.result_code == 0
                seen.append((status.trigger_id, status.result_id))
            lb.runtime.wait_idle()
            by_seq = {r.seq: r.record.trigger_id for r in _records(lb)}
            last = _records(lb)[-1].record  # what the drift watch reads: every camera's residual
            assert last.camera_residuals is not None
            assert {c.camera_id for c in last.camera_residuals} == {
                d.camera_id for d in last.detections}
            # Both parts of the 1σ, and the pose marked usable (OK) or not.
            assert last.pose_valid is (last.result == "OK")
            unc = last.uncertainty
            assert unc is not None and unc.detector_mm is not None
            assert unc.calibration_mm is not None and unc.detector_noise_px is not None
    ids = [rid for _, rid in seen]
    assert ids == sorted(set(ids)), f"result ids reused or out of order: {ids}"
    assert all(by_seq[rid] == tid for tid, rid in seen)


async def test_the_station_files_allowlist_refuses_other_plcs(tmp_path: Path) -> None:
    def only_one_plc(data: dict[str, Any]) -> None:
        data["links"] = {"modbus": {"allowlist": ["10.20.30.40"]}}

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline, only_one_plc),
                            tmp_path / "var")
    async with running_server(settings, runtime_options(), http_port=None) as rs:
        reader, writer = await asyncio.open_connection("127.0.0.1", rs.runtime.link_port("modbus"))
        # A TEACH_REFERENCE command write (fc 16 at holding 2-3), from a host not on the list.
        writer.write(b"\x00\x01\x00\x00\x00\x0b\x01\x10\x00\x02\x00\x02\x04\x00\x02\x00\x00")
        await writer.drain()
        try:
            answer = await asyncio.wait_for(reader.read(100), 3)
        except ConnectionResetError:
            answer = b""
        assert answer == b""  # closed without an answer
        writer.close()
        # the link runs in a child process: its counts come with the child's status reports
        await until(lambda: rs.runtime.status()["plc"]["rejected_connections"] >= 1,
                    "the refused connection counted")
        assert rs.runtime.status()["teach_armed"] is False


@pytest.mark.slow
@pytest.mark.parametrize("link", ["modbus", "enip", "s7"])
async def test_a_frozen_database_never_delays_the_answer(
    tmp_path: Path, postgres_cluster: Any, link: str
) -> None:
    # The relaxed deadline: a trigger merely preempted on a loaded machine must not be taken for
    # one that waited for the database (which, frozen until every trigger is answered, would
    # never answer it; SLACK_S tells "within its deadline" from that).
    url = postgres_cluster.create_database()
    path = station_file(tmp_path, "station1", relaxed_deadline)
    settings = settings_for(path, tmp_path / "var", database_url=url)
    async with running_station(settings, runtime_options(), http_port=None, link=link) as lb:
        recipe = lb.runtime.active.config
        await move_part(lb.runtime, lb.twin, recipe.T_rf_from_pf0.matrix)
        for k in range(3):  # warm: the database answers
            status, _ = await trigger(lb.twin, recipe, k, None)
            assert status.result_code == 0
        _signal_all(postgres_cluster, signal.SIGSTOP)
        try:
            answers = []
            for k in range(10, 16):
                t = time.monotonic()
                status, _ = await trigger(lb.twin, recipe, k, None)
                answers.append((k, status.result_code, status.result_id,
                                time.monotonic() - t))
            assert lb.runtime.status()["store"]["pending"] >= 1
        finally:
            _signal_all(postgres_cluster, signal.SIGCONT)
        for k, code, _rid, took in answers:
            assert code == 0, f"trigger {k}: code {code}"
            assert took < 1.0 + SLACK_S, f"trigger {k} answered after {took:.3f} s"
        lb.runtime.wait_idle(30)
        stored = {r.seq: r.record for r in _records(lb)}
        for k, code, rid, _ in answers:
            assert stored[rid].trigger_id == k and stored[rid].reason_code == code
        assert lb.runtime.services.store.measurements.verify_chain().ok



@pytest.mark.slow
@pytest.mark.skipif(profinet_peer.usable() is not None, reason=str(profinet_peer.usable()))
async def test_a_frozen_database_never_delays_the_answer_over_profinet(
    tmp_path: Path, postgres_cluster: Any
) -> None:
    """The deadline rule with the PLC on PROFINET (profinet-py on a veth pair, 4 ms cycle)."""
    url = postgres_cluster.create_database()
    name = "mvpose-station"
    with profinet_peer.veth(6) as net:
        def profinet(data: dict[str, Any]) -> None:
            data.setdefault("links", {})["profinet"] = {
                "interface": net.device_if, "station_name": name, "rpc_host": net.device_ip,
                "watchdog_s": 10.0}

        path = station_file(tmp_path, "station1", relaxed_deadline, profinet)
        settings = settings_for(path, tmp_path / "var", database_url=url)
        async with running_server(settings, runtime_options(), http_port=None) as rs, \
                profinet_peer.controller(net) as ctl:
            await ctl.run_ar(name, reduction_ratio=4)
            async with profinet_peer.plc(ctl, ready=True) as twin:
                recipe = rs.runtime.active.config
                await move_part(rs.runtime, twin, recipe.T_rf_from_pf0.matrix)
                for k in range(3):  # warm: the database answers
                    status, _ = await trigger(twin, recipe, k, None, timeout=10.0)
                    assert status.result_code == 0
                _signal_all(postgres_cluster, signal.SIGSTOP)
                try:
                    answers = []
                    for k in range(10, 16):
                        t = time.monotonic()
                        status, _ = await trigger(twin, recipe, k, None, timeout=10.0)
                        answers.append((k, status.result_code, status.result_id,
                                        time.monotonic() - t))
                    assert rs.runtime.status()["store"]["pending"] >= 1
                finally:
                    _signal_all(postgres_cluster, signal.SIGCONT)
            for k, code, _rid, took in answers:
                assert code == 0, f"trigger {k}: code {code}"
                assert took < 1.0 + SLACK_S, f"trigger {k} answered after {took:.3f} s"
            rs.runtime.wait_idle(30)
            stored = {r.seq: r.record for r in _records(rs)}
            for k, code, rid, _ in answers:
                assert stored[rid].trigger_id == k and stored[rid].reason_code == code
            assert rs.runtime.services.store.measurements.verify_chain().ok


async def test_the_apis_status_calls_reach_the_station_at_most_every_quarter_second(
    tmp_path: Path,
) -> None:
    from server.station.client import StationClient

    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    async with running_server(settings, runtime_options(), http_port=None):
        client = StationClient(settings.resolved_control_socket, status_max_age_s=0.25)
        first = await asyncio.to_thread(client.status)
        again = await asyncio.to_thread(client.status)
        assert again is first  # served from the last answer: the station was not asked
        await asyncio.sleep(0.3)
        fresh = await asyncio.to_thread(client.status)
        assert fresh is not first and fresh.station == "station1"
