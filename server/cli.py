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
    "measure": ("server.commands.measure", "measure saved images offline (no deadline)"),
    "replay": (
        "server.commands.replay",
        "re-measure archived measurements with another calibration or recipe version",
    ),
}


class CliError(Exception):
    """A user error: printed as one line, exit code 2."""


def load_station_file(path: Path) -> StationConfig:
    """The station file; a malformed one is a CliError naming file, field and value."""
    from mvpose_core.station import StationFileError, load_station

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


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    first = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(first if first in COMMANDS else None)
    args = parser.parse_args(argv)
    try:
        return int(args._module.run(args) or 0)
    except CliError as err:
        print(f"mvpose {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
