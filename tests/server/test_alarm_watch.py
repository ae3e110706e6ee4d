"""The station's alarm watch in a real station (in-process, simulated station 1, its PLC twin
attached): NOKs in a row raise NOK_STREAK at the recipe's ``nok_streak_warning`` and the next
OK clears it; an alarm left active by a previous run whose condition is gone is cleared at
start; a link with its PLC raises nothing."""

from __future__ import annotations

from pathlib import Path

from stations import relaxed_deadline, runtime_options, settings_for, station_file
from waiting import until

from server.loopback import move_part, running_station
from server.store import open_store
from server.store.alarms import AlarmFilter


async def test_nok_streak_and_a_stale_alarm(tmp_path: Path) -> None:
    settings = settings_for(station_file(tmp_path, "station1", relaxed_deadline),
                            tmp_path / "var")
    # a previous run left a camera "down"; this run's cameras are up
    store = open_store(settings.resolved_database_url, "station1")
    stale, _ = store.alarms.raise_("camera:top_left", "CAMERA_DOWN", "high", "down before")
    store.close()
    async with running_station(settings, runtime_options(), http_port=None) as lb:
        station, twin = lb.runtime, lb.twin
        alarms = station.services.store.alarms
        await until(lambda: not alarms.get(stale.id).active, "the stale alarm cleared", 30)
        limit = station.active.config.nok_streak_warning
        for k in range(1, limit + 1):  # nothing in front of the cameras: NOK
            status = await twin.cycle(k, timeout=30.0)
            assert status.result_code != 0
        await until(lambda: alarms.find(AlarmFilter(source="station", active=True)),
                    "NOK_STREAK raised", 30)
        streak = alarms.find(AlarmFilter(source="station", active=True))[0]
        assert (streak.code, streak.priority, streak.text_args["count"]) == (
            "NOK_STREAK", "medium", limit)
        await move_part(station, twin, station.active.config.T_rf_from_pf0.matrix)
        status = await twin.cycle(limit + 1, timeout=30.0)
        assert status.result_code == 0
        await until(lambda: not alarms.get(streak.id).active, "NOK_STREAK cleared", 30)
        # the link has its PLC (the twin): no link alarm was raised
        assert alarms.find(AlarmFilter(source="link:")) == []
        # nothing the watch could not write
        assert station.status()["alarms"]["last_error"] is None
