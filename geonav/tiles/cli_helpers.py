"""What the ``geonav tiles`` subcommands share: their argparse types and the scene line.

:mod:`geonav.tiles.cli` (ingest, synth) and :mod:`geonav.tiles.cli_more` (fetch, info,
preview) both import from here; neither imports the other's helpers.
"""

from __future__ import annotations

import argparse

from geonav.cliutil import bbox_arg, lonlat_arg, positive_int
from geonav.errors import ConfigError

#: argparse types shared by the tiles subcommands (kept under their old names).
parse_lonlat = lonlat_arg
parse_bbox = bbox_arg


def parse_bands(text: str) -> tuple[int, ...]:
    """argparse type of --bands: '4,3,2' or '1' (1-based, like GDAL)."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (1, 3):
        raise argparse.ArgumentTypeError(f"{text!r}: give three bands R,G,B like 4,3,2, or one")
    return tuple(positive_int(p) for p in parts)


def parse_subdomains(text: str) -> tuple[str, ...]:
    """The values of a tile URL's {s}: letters ('abc') or comma-separated names."""
    parts = [s.strip() for s in text.split(",")] if "," in text else list(text)
    if not all(parts) or not all(s.replace("-", "").isalnum() for s in parts):
        raise ConfigError(f"--subdomains {text!r}: give letters like 'abc' or names like "
                          "'t0,t1,t2' (letters, digits, '-')")
    return tuple(parts)
