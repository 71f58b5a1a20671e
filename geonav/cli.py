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
from geonav.cliutil import (
    GeonavParser,
    apply_verbosity,
    common_options,
    needs_subcommand,
    one_line_warnings,
    oserror_line,
)
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
        parents=[common_options(root=True)],
    )
    parser.add_argument("--version", action="version", version=f"geonav {__version__}")
    parser.set_defaults(handler=needs_subcommand(parser))
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
    """Run the ``geonav`` command; returns the exit status.

    Every expected failure ends in one line on stderr and exit status 2 (130 for Ctrl-C,
    at any moment, start-up included); ``-v`` adds the traceback above that line.
    """
    args: argparse.Namespace | None = None
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        level = apply_verbosity(args)
        logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
        one_line_warnings()
        handler = getattr(args, "handler", None)
        if handler is None:
            parser.print_help()
            return 0
        return int(handler(args) or 0)
    except KeyboardInterrupt:
        print("geonav: interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # noqa: BLE001 - the expected classes become one line
        line = error_line(err, args)
        if line is None:
            raise  # not an expected failure: a bug, whose traceback says where
        if _verbose(args, argv):
            import traceback

            traceback.print_exc()
        print(f"geonav: error: {' '.join(line.split())}", file=sys.stderr)
        return 2


def _verbose(args: argparse.Namespace | None, argv: Sequence[str] | None) -> bool:
    if args is not None:
        return bool(getattr(args, "verbose", 0))
    words = sys.argv[1:] if argv is None else list(argv)
    return any(w in ("-v", "-vv", "--verbose") for w in words)


def error_line(err: BaseException, args: argparse.Namespace | None = None) -> str | None:
    """The one line (without the ``geonav: error:`` prefix) for an expected failure, naming
    the input and the fix; None for anything else (a bug)."""
    if isinstance(err, GeonavError):
        return str(err)
    if isinstance(err, UnicodeDecodeError):
        where = _undecodable_input(args)
        return (f"{where or 'an input file'} is not UTF-8 text ({err.reason} at byte "
                f"{err.start}); save it as UTF-8" + ("" if where else
                                                     " (the TOML or JSON file given)"))
    if isinstance(err, OSError):  # an unwritable --out, a full disk: the path and the reason
        return oserror_line(err)
    if type(err).__module__.startswith("rasterio"):  # RasterioError, CPLE_* (GDAL)
        return (f"GDAL could not read or write a raster ({type(err).__name__}: "
                f"{' '.join(str(err).split())[:300]}); check the file it names is a raster "
                "GDAL can open and that its disk has room")
    if isinstance(err, MemoryError):
        return ("out of memory: the input asks for more than this machine has; ask for less "
                "(a smaller --bbox or coarser --gsd, a larger lattice --step, fewer workers or "
                "a smaller batch)")
    if isinstance(err, OverflowError):
        return (f"a number is out of range ({err}); check the numbers on the command line "
                "and in the input files")
    return None


#: Suffixes of the text inputs geonav reads (configs, task sets, manifests).
TEXT_SUFFIXES = (".toml", ".json", ".jsonl", ".txt", ".csv", ".md")


def _undecodable_input(args: argparse.Namespace | None) -> str | None:
    """The first file named in ``args`` that is not UTF-8 text (to name it in the error)."""
    import os

    if args is None:
        return None
    for value in vars(args).values():
        for item in value if isinstance(value, list | tuple) else [value]:
            if not isinstance(item, str | os.PathLike) or not os.path.isfile(item) or \
                    os.path.splitext(item)[1].lower() not in TEXT_SUFFIXES:
                continue  # rasters, tile databases, checkpoints: binary on purpose
            try:
                if os.path.getsize(item) > 64 << 20:
                    continue
                with open(item, "rb") as f:
                    f.read().decode("utf-8")
            except UnicodeDecodeError:
                return str(item)
            except OSError:
                continue
    return None


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
