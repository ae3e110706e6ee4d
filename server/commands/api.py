"""``mvpose api --station FILE``: the API process alone (REST over the store, the operator page,
the control channel's client), at a lower CPU priority than the station process."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import socket
from pathlib import Path

import uvicorn

from server.commands import options

log = logging.getLogger(__name__)

API_NICE = 5  # below the station process: a trigger never waits for an HTTP request's CPU


def add_arguments(parser: argparse.ArgumentParser) -> None:
    options.add_common(parser)
    options.add_api_options(parser)


def run(args: argparse.Namespace) -> int:
    from server.app import create_app
    from server.station.client import StationClient

    options.setup_logging(args.log_level)
    settings = options.settings_from(args)
    options.station_with_links(args, settings.station)  # a malformed file stops start-up here too
    host, port = options.api_address(args)
    with contextlib.suppress(OSError):  # not permitted: the API runs at the normal priority
        os.nice(API_NICE)
    app = create_app(settings, StationClient(settings.resolved_control_socket))
    # An open Live page streams events: wait for open responses at most 3 s on SIGTERM.
    config = uvicorn.Config(app, host=host, port=port, log_level=args.log_level, lifespan="on",
                            timeout_graceful_shutdown=3)
    server = _Server(config, settings.data_dir / API_ADDRESS_FILE)
    server.run()
    # uvicorn returns normally when the lifespan failed at start-up: report it as a failure.
    return 0 if server.started else 1


API_ADDRESS_FILE = "api.json"  # where the API process says where it listens (port 0: any)


class _Server(uvicorn.Server):
    """uvicorn's server that writes its bound address to the data directory once it listens, so
    the supervisor and tools find an API started on port 0."""

    def __init__(self, config: uvicorn.Config, address_file: Path) -> None:
        super().__init__(config)
        self.address_file = address_file

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets)
        if not self.started or not self.servers:
            return
        host, port = self.servers[0].sockets[0].getsockname()[:2]
        tmp = self.address_file.with_suffix(".tmp")
        tmp.write_text(json.dumps({"pid": os.getpid(), "host": host, "port": port}))
        tmp.replace(self.address_file)
