"""``mvpose station --station FILE``: the station process alone (cameras, links, pipeline, store
writes, control channel; no HTTP). `mvpose serve` runs it next to `mvpose api`; a deployment with
two containers runs each command in its own."""

from __future__ import annotations

import argparse

from server.cli import CliError
from server.commands import options


def add_arguments(parser: argparse.ArgumentParser) -> None:
    options.add_common(parser)
    options.add_station_options(parser)


def run(args: argparse.Namespace) -> int:
    from drivers.errors import DriverInitError
    from server.pipeline import PipelineOptions, auto_detect_processes
    from server.station import scheduling
    from server.station.core import StationOptions
    from server.station.process import run_station

    options.setup_logging(args.log_level)
    settings = options.settings_from(args)
    station = options.station_with_links(args, settings.station)
    options.check_link_ports(station)
    procs = args.detect_processes
    if procs is None:
        procs = auto_detect_processes()
    if procs < 0:
        raise CliError(f"--detect-processes must be >= 0, got {procs}")
    priority = options.number(args.trigger_priority, "MVPOSE_TRIGGER_PRIORITY",
                              scheduling.DEFAULT_PRIORITY, int, "an integer 0-99")
    if not 0 <= priority <= 99:
        raise CliError(f"--trigger-priority must be 0-99 (0: normal scheduler), got {priority}")
    keep = options.number(args.sim_keep_poses, "MVPOSE_SIM_KEEP_POSES", 0, int,
                          "an integer >= 0")
    if keep < 0:
        raise CliError(f"--sim-keep-poses must be >= 0, got {keep}")
    # before anything starts: every thread and worker process inherits the policy
    cpu = scheduling.enter(priority)
    try:
        return run_station(settings, station, StationOptions(
            sim_part_at_reference=True, sim_keep_poses=keep,
            pipeline=PipelineOptions(detect_processes=procs)), cpu)
    except DriverInitError as err:  # a link that cannot listen (taken since the check above)
        raise CliError(str(err)) from None
