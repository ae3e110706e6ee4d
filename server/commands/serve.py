"""``mvpose serve --station FILE``: the station server as two supervised processes.

The station process (`mvpose station`: cameras, links, pipeline, store writes) and the API
process (`mvpose api`: REST, operator page) share the station file, the data directory and the
control socket in it; server.supervisor restarts either when it dies.
"""

from __future__ import annotations

import argparse
import json
import sys
import urllib.request

from server.cli import check_port_free
from server.commands import options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    options.add_common(parser)
    options.add_station_options(parser)
    options.add_api_options(parser)


def run(args: argparse.Namespace) -> int:
    from drivers.links import link_settings
    from server.commands.api import API_ADDRESS_FILE
    from server.station.alarms import ProcessAlarms
    from server.station.client import StationClient, StationDownError
    from server.supervisor import Child, Supervisor, python_argv

    options.setup_logging(args.log_level)
    # Checked here first, so a malformed file or option stops start-up with one line.
    settings = options.settings_from(args)
    station = options.station_with_links(args, settings.station)
    host, port = options.api_address(args)
    if args.rest_yield_ms is not None or args.answer_read_wait_ms is not None:
        print("mvpose serve: --rest-yield-ms and --answer-read-wait-ms are ignored: the API "
              "runs in a process of its own", file=sys.stderr)
    check_port_free(host, port)
    options.check_link_ports(station)
    common = ["--station", str(settings.station), "--data-dir", str(settings.data_dir),
              "--log-level", args.log_level]
    station_argv = common + options.forward(args, [*options.LINK_OPTIONS, "detect_processes",
                                                     "trigger_priority", "sim_keep_poses"])
    api_argv = common + ["--host", host, "--port", str(port)]
    client = StationClient(settings.resolved_control_socket, timeout_s=1.0)

    def station_ready() -> bool:
        try:
            client.call("ping")
        except StationDownError:
            return False
        return True

    address_file = settings.data_dir / API_ADDRESS_FILE
    address_file.unlink(missing_ok=True)

    def api_ready() -> bool:
        try:  # the API process writes where it listens (port 0: the one it was given)
            bound = json.loads(address_file.read_text())["port"]
            with urllib.request.urlopen(
                    f"http://{_connect_host(host)}:{bound}/api/v1/health/live", timeout=1.0):
                return True
        except (OSError, ValueError, KeyError):
            return False

    links = "".join(f", {name} {getattr(cfg, 'host', '')}:{getattr(cfg, 'port', '')}"
                    for name, cfg in link_settings(station.links).items()
                    if getattr(cfg, "enabled", True))
    print(f"mvpose: station {station.name!r}: REST http://{host}:{port}/api/v1 (docs /docs)"
          f"{links}", flush=True)
    mqtt = station.plant is not None and station.plant.mqtt is not None
    alarms = ProcessAlarms(settings.resolved_database_url, station.name,
                           f"{station.plant.topic_prefix(station.name)}/alarms"
                           if mqtt and station.plant is not None else None)
    try:
        return Supervisor([
            Child("station", python_argv("station", station_argv), station_ready,
                  on_change=alarms),
            Child("api", python_argv("api", api_argv), api_ready),
        ]).run()
    finally:
        alarms.close()


def _connect_host(host: str) -> str:
    return "127.0.0.1" if host in ("0.0.0.0", "") else ("[::1]" if host == "::" else host)
