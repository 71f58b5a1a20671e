"""The ``geonav`` command: thin argparse front-end over the library.

Each subpackage registers its own subcommands (``add_parser(subparsers)``)
and handlers; this module wires them, sets up logging and turns a
:class:`geonav.errors.GeonavError` into one line on stderr and exit code 2.
Subcommand modules are imported lazily where they pull in heavy libraries.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from geonav import __version__
from geonav.cliutil import GeonavParser, one_line_warnings, oserror_line
from geonav.errors import GeonavError

#: Modules that provide ``add_parser(subparsers)``; missing ones are skipped.
SUBCOMMAND_MODULES = (
    "geonav.tiles.cli",
    "geonav.tasks_cli",
    "geonav.policy.cli",
    "geonav.experiments.cli",
    "geonav.mavlink_bridge.cli",
    "geonav.demo",
)


def build_parser() -> argparse.ArgumentParser:
    parser = GeonavParser(
        prog="geonav",
        description="Learn drone visual navigation from aerial imagery and fly it over MAVLink.",
    )
    parser.add_argument("--version", action="version", version=f"geonav {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0,
                        help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as err:
            if err.name and name.startswith(err.name):
                continue  # that part of the toolkit is not installed/built yet
            raise
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    one_line_warnings()
    handler = getattr(args, "handler", None)
    if handler is None:
        parser.print_help()
        return 0
    try:
        return int(handler(args) or 0)
    except GeonavError as err:
        print(f"geonav: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except OSError as err:  # an unwritable --out, a full disk: the path and the reason
        print(f"geonav: error: {oserror_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("geonav: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
