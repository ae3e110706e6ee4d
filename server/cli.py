"""The ``mvpose`` command line: one sub-command per module, imported only when it is used."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mvpose_core.station import RecipeConfig, StationConfig

# name -> (module, one-line help). Each module defines ``add_arguments(parser)`` and
# ``run(args) -> int``; importing lazily keeps ``mvpose --help`` fast and free of heavy imports.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("server.commands.demo", "run the station demo on simulated hardware"),
    "serve": ("server.commands.serve", "run the station server (station + API processes)"),
    "station": ("server.commands.station", "run the station process alone (no HTTP)"),
    "api": ("server.commands.api", "run the API process alone (REST, operator page)"),
    "simulate": ("server.commands.simulate", "accuracy studies and station planning"),
    "calibrate": ("server.commands.calibrate", "camera, stereo, hand-eye and station calibration"),
    "validate": (
        "server.commands.validate",
        "commissioning validation against ground-truth offsets",
    ),
    "token": ("server.commands.token", "create, list and revoke API tokens in the store"),
    "user": ("server.commands.user",
             "the operator page's users: add, list, disable, enable, reset, their audit trail"),
    "measure": ("server.commands.measure", "measure saved images offline (no deadline)"),
    "gauge": (
        "server.commands.gauge",
        "gauge capability studies (type 1, type 3, linearity) with an HTML and PDF report",
    ),
    "replay": (
        "server.commands.replay",
        "re-measure archived measurements with another calibration or recipe version",
    ),
}


class CliError(Exception):
    """A user error: printed as one line, exit code 2."""


def load_station_file(path: Path) -> StationConfig:
    """The station file; a malformed one is a CliError naming file, field and value."""
    from mvpose_core.station import StationFileError
    from server.links import load_station

    try:
        return load_station(path)
    except StationFileError as err:
        raise CliError(str(err)) from None


def station_recipe(station: StationConfig, name: str | None) -> RecipeConfig:
    """One of the station's recipes (None: its default); an unknown name is a CliError."""
    try:
        return station.recipe(name)
    except KeyError as err:
        raise CliError(str(err.args[0])) from None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mvpose", description="multi-view pose station server")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if only is None or only == name:
            module = importlib.import_module(module_name)
            module.add_arguments(p)
            p.set_defaults(_module=module)
    return parser


# Commands that start the API (uvicorn runs the app's lifespan, where a bad setting would
# otherwise end as a logged traceback and, under `mvpose serve`, an API process restarted forever).
SERVER_COMMANDS = frozenset({"serve", "api"})


def one_line(message: object) -> str:
    """A message on one line: YAML's context lines and a list of problems joined by '; '."""
    lines = [x.strip() for x in str(message).splitlines()]
    return "; ".join(x for x in lines if x and set(x) != {"^"})


def check_port_free(host: str, port: int, what: str = "REST address",
                    hint: str = "pass --port / set MVPOSE_PORT") -> None:
    """CliError naming ``what`` and the address when ``host:port`` cannot be bound (in use,
    not ours); ``hint`` says how to choose another."""
    import socket

    if port == 0:
        return
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds it
        try:
            s.bind((host, port))
        except OSError as err:
            raise CliError(f"{what} {host}:{port} is not free ({err.strerror}): stop "
                           f"what listens there, or {hint}") from None


def check_start_up(args: argparse.Namespace) -> None:
    """What would stop a server only once it runs, checked before anything starts: the
    bootstrap token's length and (``mvpose api``) the REST address."""
    import os

    if args.command not in SERVER_COMMANDS:
        return
    if "MVPOSE_LINE_VIEW_PUBLIC" in os.environ:  # a security setting must not be ignored
        raise CliError("MVPOSE_LINE_VIEW_PUBLIC is no longer read: the kiosk line view is the "
                       "station file's `page: {kiosk: true}`; unset the variable")
    secret = os.environ.get("MVPOSE_BOOTSTRAP_TOKEN")
    if secret is not None:
        from server.auth import check_bootstrap_secret
        from server.errors import DomainError

        try:
            check_bootstrap_secret(secret)
        except DomainError as err:
            raise CliError(err.detail) from None
    if args.command == "api":  # `mvpose serve` checks the address itself before its children
        from server.commands.options import api_address

        check_port_free(*api_address(args))


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(first if first in COMMANDS else None)
    args = parser.parse_args(argv)
    from mvpose_core.station import StationFileError
    from server.errors import DomainError

    try:
        check_start_up(args)
        return int(args._module.run(args) or 0)
    except CliError as err:
        print(f"mvpose {args.command}: error: {one_line(err)}", file=sys.stderr)
        return 2
    except (StationFileError, DomainError) as err:
        print(f"mvpose {args.command}: error: {one_line(err)}", file=sys.stderr)
        return 1
    except OSError as err:  # a file or address the command needs: name it, no traceback
        where = f" ({err.filename})" if err.filename else ""
        print(f"mvpose {args.command}: error: {err.strerror or err}{where}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    # `python -m server.cli`: run the module the commands import (server.cli), not this copy
    # named __main__, whose CliError would be another class than the one they raise.
    from server.cli import main as _main

    raise SystemExit(_main())
