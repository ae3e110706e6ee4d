"""The options `mvpose serve`, `mvpose station` and `mvpose api` share, and how they resolve.

Each value comes from the command line, else from its ``MVPOSE_*`` environment variable, else
from the station file (link settings), else from the default; docs/operations.md lists them in
one table. A bad value stops start-up with one line naming the option or the variable.
"""

from __future__ import annotations

import argparse
import logging
import os
from pathlib import Path
from typing import Any, TypeVar

from server.cli import CliError, load_station_file

_N = TypeVar("_N", int, float)

# option → (environment variable, link backend, field of its settings, what it is); the value
# is checked by the backend's own settings model (drivers.links.settings_model)
LINK_OPTIONS: dict[str, tuple[str, str, str, str]] = {
    "plc_host": ("MVPOSE_PLC_HOST", "modbus", "host", "Modbus/TCP address to listen on"),
    "plc_port": ("MVPOSE_PLC_PORT", "modbus", "port", "Modbus/TCP port"),
    "plc_unit_id": ("MVPOSE_PLC_UNIT_ID", "modbus", "unit_id",
                    "Modbus unit id answered (0 = any)"),
    "plc_word_order": ("MVPOSE_PLC_WORD_ORDER", "modbus", "word_order", "ABCD or CDAB"),
    "plc_allowlist": ("MVPOSE_PLC_ALLOWLIST", "modbus", "allowlist",
                      "comma-separated PLC addresses or networks allowed to connect"),
    "plc_watchdog_s": ("MVPOSE_PLC_WATCHDOG_S", "modbus", "watchdog_s",
                       "PLC heartbeat timeout, s"),
    "plc_trigger_hold_s": ("MVPOSE_PLC_TRIGGER_HOLD_S", "modbus", "trigger_hold_s",
                           "TRIGGER held this long after the answer is an error, s"),
}


def add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--station", type=Path,
                        help="station YAML file (default: $MVPOSE_STATION)")
    parser.add_argument("--data-dir", type=Path,
                        help="SQLite database, image archive, journal and control socket "
                        "(default: $MVPOSE_DATA_DIR or ./var)")
    parser.add_argument("--log-level", default="info",
                        choices=["debug", "info", "warning", "error"])


def add_station_options(parser: argparse.ArgumentParser) -> None:
    for name, (env, backend, field, what) in LINK_OPTIONS.items():
        parser.add_argument("--" + name.replace("_", "-"), dest=name, default=None,
                            help=f"{what} (default: ${env}, else the station file's "
                            f"links.{backend}.{field})")
    parser.add_argument("--detect-processes", type=int, default=None,
                        help="worker processes for mark detection (0 = on the station's trigger "
                        "thread; default: none below 8 cores, else 4: a worker detects one image "
                        "alone, see docs/performance.md)")
    parser.add_argument("--trigger-priority", type=int, default=None,
                        help="real-time (SCHED_FIFO) priority of the station process's trigger "
                        "path, 1-99, 0 = the normal scheduler (default: "
                        "$MVPOSE_TRIGGER_PRIORITY, else 10; needs CAP_SYS_NICE, else the "
                        "station runs at normal priority and says so in its status)")
    parser.add_argument("--sim-keep-poses", type=int, default=None,
                        help="simulated cameras: keep the renderings of this many recent part "
                        "poses, so that a rehearsal moving the part back to one of them takes "
                        "no rendering (default: $MVPOSE_SIM_KEEP_POSES, else 0)")


def add_api_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", help="REST address (default: $MVPOSE_HOST or 127.0.0.1)")
    parser.add_argument("--port", type=int, help="REST port (default: $MVPOSE_PORT or 8000)")
    # Kept so that existing start scripts still run: the API has its own process now, so there
    # is nothing left to hold back for a trigger.
    for old in ("--rest-yield-ms", "--answer-read-wait-ms"):
        parser.add_argument(old, type=float, default=None, help=argparse.SUPPRESS)


def number(given: Any, name: str, default: _N, kind: type[_N], what: str) -> _N:
    """The command-line value if given, else ``$name`` as ``kind``, else ``default``."""
    raw = given if given is not None else os.environ.get(name)
    if raw is None or raw == "":
        return default
    try:
        return kind(raw)
    except ValueError:
        src = "option" if given is not None else "environment variable"
        raise CliError(f"{src} {name}: expected {what}, got {raw!r}") from None


def settings_from(args: argparse.Namespace) -> Any:
    """Settings from the environment, with --station and --data-dir on top."""
    from pydantic import ValidationError

    from server.settings import Settings

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
    return settings


def station_with_links(args: argparse.Namespace, path: Path) -> Any:
    """The station file, its link settings overridden from the command line and env (each value
    checked by its backend's settings model; the file's own blocks are checked on load)."""
    from pydantic import ValidationError

    from drivers.links import link_settings, settings_model

    station = load_station_file(path)
    blocks = {name: cfg.model_dump() for name, cfg in link_settings(station.links).items()}
    changed: set[str] = set()
    for name, (env, backend, field, _what) in LINK_OPTIONS.items():
        given = getattr(args, name, None)
        raw = given if given is not None else os.environ.get(env)
        if raw is None or raw == "":
            continue
        data = blocks.setdefault(backend, {})
        if field == "allowlist":
            data[field] = tuple(x.strip() for x in str(raw).split(",") if x.strip())
        else:
            data[field] = raw
        try:
            settings_model(backend).model_validate(data)
        except ValidationError as err:
            src = "--" + name.replace("_", "-") if given is not None else env
            raise CliError(f"{src}: {err.errors()[0]['msg']} (value: {raw!r})") from None
        changed.add(backend)
    if not changed:
        return station
    links = dict(station.links)
    for backend in changed:  # as plain data, as the file has it
        links[backend] = settings_model(backend).model_validate(blocks[backend]).model_dump(
            mode="json")
    return station.model_copy(update={"links": links})


def check_link_ports(station: Any) -> None:
    """CliError naming the link and its address when a link's port is taken (before anything
    starts: a link that fails to listen later would stop the station with a traceback). A
    client link's address is its PLC's (drivers.links.CLIENTS): nothing to check."""
    from drivers.links import CLIENTS, link_settings
    from server.cli import check_port_free

    for backend, cfg in link_settings(station.links).items():
        if backend in CLIENTS:
            continue
        host, port = getattr(cfg, "host", None), getattr(cfg, "port", None)
        if not getattr(cfg, "enabled", True) or not isinstance(host, str) \
                or not isinstance(port, int):
            continue
        hint = f"change links.{backend}.port in the station file"
        options = [(name, env) for name, (env, b, field, _) in LINK_OPTIONS.items()
                   if (b, field) == (backend, "port")]
        if options:
            name, env = options[0]
            hint += f", or pass --{name.replace('_', '-')} / set {env}"
        check_port_free(host, port, f"{backend} link address", hint)


def setup_logging(level: str) -> None:
    logging.basicConfig(level=level.upper(),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def api_address(args: argparse.Namespace) -> tuple[str, int]:
    host = args.host or os.environ.get("MVPOSE_HOST") or "127.0.0.1"
    port = number(args.port, "MVPOSE_PORT", 8000, int, "a port number")
    if not 0 <= port <= 65535:
        raise CliError(f"REST port must be 0 ... 65535, got {port}")
    return host, port


def forward(args: argparse.Namespace, names: list[str]) -> list[str]:
    """The given options again, as command-line arguments for a child process."""
    out: list[str] = []
    for name in names:
        value = getattr(args, name, None)
        if value is not None:
            out += ["--" + name.replace("_", "-"), str(value)]
    return out
