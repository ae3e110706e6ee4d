"""The station process: open the store, start the station and its control channel, run until
SIGTERM or SIGINT, and stop in order (links first, so no trigger is taken that cannot finish)."""

from __future__ import annotations

import logging
import os
import signal
import sys
import threading
import time
from typing import Any

from mvpose_core.station import StationConfig
from server.settings import Settings
from server.state import Services, open_services
from server.station.alarms import AlarmWatch, AlarmWatchOptions
from server.station.control import ControlServer
from server.station.core import Station, StationOptions
from server.station.mqtt import MqttPublisher

log = logging.getLogger(__name__)


class StationProcess:
    """A started station with its control channel (``mvpose station``; tests run it in-process)."""

    def __init__(self, settings: Settings, station: StationConfig,
                 options: StationOptions | None = None,
                 alarm_options: AlarmWatchOptions | None = None) -> None:
        self.settings = settings
        self.station = Station(station, options)
        self.control: ControlServer | None = None
        self.publisher: MqttPublisher | None = None  # only with a plant.mqtt block
        self.alarm_options = alarm_options
        self.alarms: AlarmWatch | None = None
        self._services: Services | None = None

    def start(self) -> None:
        services = open_services(self.settings, bootstrap=False)
        self._services = services
        try:
            self.publisher = MqttPublisher.for_station(self.station.station,
                                                       services.software_version)
            self.station.start(services, self.publisher.sink(services) if self.publisher
                               else None)
            if self.publisher is not None:
                self.publisher.start(self.station)
                self.station.status_parts["mqtt"] = self.publisher.status
            self.alarms = AlarmWatch(self.station, services.store.alarms, self.alarm_options)
            self.alarms.start()
            self.station.status_parts["alarms"] = self.alarms.status
            control = ControlServer(self.station, self.settings.resolved_control_socket)
            self.station.run_on_loop(control.start(), timeout=10)
            self.control = control
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        if self.control is not None and self.station.loop is not None:
            try:
                self.station.run_on_loop(self.control.stop(), timeout=5)
            except Exception:
                log.exception("the control channel did not stop cleanly")
        self.control = None
        if self.alarms is not None:
            self.alarms.stop()
            self.alarms = None
        if self.publisher is not None:
            self.publisher.stop()
            self.publisher = None
        self.station.stop()
        if self._services is not None:
            self._services.close()
            self._services = None


def run_station(settings: Settings, station: StationConfig, options: StationOptions,
                cpu: dict[str, Any] | None = None) -> int:
    """Run until SIGTERM/SIGINT; 0 on a clean stop. ``cpu``: the scheduling policy the process
    runs under (server.station.scheduling), shown in the status."""
    # A thread that wants the GIL (the trigger thread, the links' loop) gets it from a busy one
    # (the database commit, a store query for an OPC UA client) within 1 ms instead of CPython's
    # default 5 ms.
    sys.setswitchinterval(0.001)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    proc = StationProcess(settings, station, options)
    if cpu is not None:
        proc.station.status_parts["cpu"] = lambda: cpu
    t = time.monotonic()
    proc.start()
    st = proc.station
    links = ", ".join(f"{k} {v.get('port')}" for k, v in st.status()["links"].items())
    print(f"mvpose station {station.name!r}: ready in {time.monotonic() - t:.1f} s; links: "
          f"{links}; control {settings.resolved_control_socket}", flush=True)
    stop.wait()
    log.info("station %s: stopping", station.name)
    proc.stop()
    # Everything this process owns is closed: the links, the cameras, the journal (fsynced) and
    # the database. The interpreter's own teardown of the camera SDKs' extension modules took
    # 2-3 s more on a loaded 2-core machine, past the 5 s a container runtime waits after
    # SIGTERM, so the process ends here.
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
