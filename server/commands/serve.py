"""``mvpose serve --station FILE``: the station server (REST, PLC link, pipeline) on uvicorn."""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path
from typing import TypeVar

from server.cli import CliError, load_station_file

_N = TypeVar("_N", int, float)


def _number(given: _N | None, name: str, default: _N, kind: type[_N], what: str) -> _N:
    """The command-line value if given, else ``$name`` as ``kind``, else ``default``; a bad
    environment value names the variable."""
    if given is not None:
        return given
    raw = os.environ.get(name)
    if raw is None or raw == "":
        return default
    try:
        return kind(raw)
    except ValueError:
        raise CliError(f"environment variable {name}: expected {what}, got {raw!r}") from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--station", type=Path,
                        help="station YAML file (default: $MVPOSE_STATION)")
    parser.add_argument("--host", help="REST address (default: $MVPOSE_HOST or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="REST port (default: $MVPOSE_PORT or 8000)")
    parser.add_argument("--plc-host",
                        help="Modbus/TCP address (default: $MVPOSE_PLC_HOST or 127.0.0.1)")
    parser.add_argument("--plc-port", type=int,
                        help="Modbus/TCP port (default: $MVPOSE_PLC_PORT or 502)")
    parser.add_argument("--data-dir", type=Path,
                        help="SQLite database and image archive "
                        "(default: $MVPOSE_DATA_DIR or ./var)")
    parser.add_argument("--detect-processes", type=int, default=None,
                        help="worker processes for mark detection (0 = threads in the server "
                        "process; default: none below 4 cores, else half the cores, at most 4)")
    parser.add_argument("--rest-yield-ms", type=float, default=None,
                        help="an HTTP request arriving during a trigger waits for it, at most "
                        "this long (default MVPOSE_REST_YIELD_MS or 100; 0 = never)")
    parser.add_argument("--answer-read-wait-ms", type=float, default=None,
                        help="after a PLC trigger's result is ready, HTTP requests keep waiting "
                        "until the PLC has read it, at most this long (default "
                        "MVPOSE_ANSWER_READ_WAIT_MS or 20; set it near the PLC's task cycle)")
    parser.add_argument("--log-level", default="info",
                        choices=["debug", "info", "warning", "error"])


def run(args: argparse.Namespace) -> int:
    # Heavy imports only when the command runs (`mvpose --help` stays fast).
    import uvicorn
    from pydantic import ValidationError

    from server.app import create_app
    from server.pipeline import PipelineOptions, auto_detect_processes
    from server.runtime import RuntimeOptions, StationRuntime
    from server.settings import Settings

    logging.basicConfig(level=args.log_level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    overrides: dict[str, object] = {}
    if args.station is not None:
        overrides["station"] = args.station
    if args.data_dir is not None:
        overrides["data_dir"] = args.data_dir
    try:
        settings = Settings(**overrides)  # type: ignore[arg-type]
    except ValidationError as err:
        first = err.errors()[0]
        raise CliError(f"settings: MVPOSE_{str(first['loc'][0]).upper()}: {first['msg']} "
                       f"(value: {first.get('input')!r})") from None
    if settings.station is None:
        raise CliError("no station file: pass --station FILE or set MVPOSE_STATION")
    # Checked here too, so a malformed file stops start-up before anything opens.
    station = load_station_file(settings.station)
    host = args.host or os.environ.get("MVPOSE_HOST") or "127.0.0.1"
    port = _number(args.port, "MVPOSE_PORT", 8000, int, "a port number")
    plc_host = args.plc_host or os.environ.get("MVPOSE_PLC_HOST") or "127.0.0.1"
    plc_port = _number(args.plc_port, "MVPOSE_PLC_PORT", 502, int, "a port number")
    if args.detect_processes is None:
        args.detect_processes = auto_detect_processes()
    if args.detect_processes < 0:
        raise CliError(f"--detect-processes must be >= 0, got {args.detect_processes}")
    rest_yield_ms = _number(args.rest_yield_ms, "MVPOSE_REST_YIELD_MS", 100.0, float, "a number")
    if not 0.0 <= rest_yield_ms <= 1000.0:
        raise CliError(f"--rest-yield-ms must be within 0 ... 1000, got {rest_yield_ms}")
    answer_wait_ms = _number(args.answer_read_wait_ms, "MVPOSE_ANSWER_READ_WAIT_MS", 20.0, float,
                             "a number")
    if not 0.0 <= answer_wait_ms <= 1000.0:
        raise CliError(f"--answer-read-wait-ms must be within 0 ... 1000, got {answer_wait_ms}")
    runtime = StationRuntime(station, RuntimeOptions(
        plc_host=plc_host, plc_port=plc_port, sim_part_at_reference=True,
        pipeline=PipelineOptions(detect_processes=args.detect_processes),
        rest_yield_ms=rest_yield_ms, answer_read_wait_ms=answer_wait_ms))
    app = create_app(settings, runtime)
    print(f"mvpose: station {station.name!r}: REST http://{host}:{port}/api/v1 "
          f"(docs /docs), Modbus/TCP {plc_host}:{plc_port}", flush=True)
    config = uvicorn.Config(app, host=host, port=port, log_level=args.log_level, lifespan="on")
    server = uvicorn.Server(config)
    server.run()
    # uvicorn returns normally when the lifespan failed at start-up: report it as a failure.
    return 0 if server.started else 1
