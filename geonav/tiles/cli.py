"""``geonav tiles ...``: ingest imagery into scene packages and inspect them."""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

from geonav.cliutil import (
    add_command_group,
    finite_float,
    nonneg_int,
    positive_float,
    seed_int,
)
from geonav.errors import GeonavWarning
from geonav.tiles import DEFAULT_MEMORY_BUDGET_MB, DSM_UNIT_CHOICES, cli_more, lidar, sample_data
from geonav.tiles.cli_helpers import parse_bands, parse_bbox, parse_lonlat

__all__ = ["add_parser", "parse_bbox", "parse_lonlat", "run_ingest", "run_synth"]


def add_parser(sub: argparse._SubParsersAction) -> None:
    tsub = add_command_group(sub, "tiles",
                             help="ingest imagery into scene packages, inspect scenes",
                             metavar="TILES_COMMAND")

    p = tsub.add_parser("ingest", help="GeoTIFFs, XYZ tile folders, MBTiles -> scene package")
    p.add_argument("sources", nargs="+",
                   help="GeoTIFF/COG files in any CRS, folders of {z}/{x}/{y}.png|jpg|webp "
                   "tiles, .mbtiles files (mosaicked in order, first wins)")
    p.add_argument("--tms", action="store_true",
                   help="tile folders count rows from the south (TMS) instead of XYZ")
    p.add_argument("--zoom", type=nonneg_int,
                   help="zoom level to read from tile folders/MBTiles (default: the highest)")
    p.add_argument("--name", required=True, help="scene name, e.g. A")
    p.add_argument("--out", required=True, help="scene package folder to write")
    p.add_argument("--dsm", help="surface model raster of absolute heights (any CRS)")
    p.add_argument("--dem", help="ground height raster (default: --ground-alt or estimated)")
    p.add_argument("--ground-alt", type=finite_float, help="ground height AMSL in metres")
    p.add_argument("--gsd", type=positive_float,
                   help="scene GSD in m/px (default: the sources' finest)")
    p.add_argument("--bbox", type=parse_bbox, help="cut to west,south,east,north (degrees)")
    p.add_argument("--origin", type=parse_lonlat, help="scene origin lon,lat[,alt]")
    p.add_argument("--bands", type=parse_bands,
                   help="1-based bands of GeoTIFF sources to use as R,G,B (e.g. 4,3,2 for "
                   "Landsat 8) or one grey band; default: the file's colour interpretation")
    p.add_argument("--dsm-units", choices=DSM_UNIT_CHOICES,
                   help="unit of the --dsm/--dem values (default: the file's band unit or "
                   "vertical CRS, else its horizontal CRS unit, with a warning)")
    p.add_argument("--memory-budget", type=positive_float, metavar="MIB",
                   help=f"refuse reads and scene grids above this many MiB (default "
                   f"{DEFAULT_MEMORY_BUDGET_MB})")
    p.add_argument("--attribution", default="", help="licence/attribution text you hold")
    p.add_argument("--compress", default="JPEG", choices=["JPEG", "DEFLATE"])
    p.add_argument("--force", action="store_true", help="replace an existing package")
    p.set_defaults(handler=run_ingest)

    p = tsub.add_parser("synth", help="synthesise a scene (GeoTIFF in EPSG:3857 + DSM), ingest it")
    p.add_argument("--kind", default="residential", choices=["residential", "campus", "wild",
                                                                  "mixed"])
    p.add_argument("--name", help="scene name (default: the kind)")
    p.add_argument("--out", required=True, help="scene package folder to write")
    p.add_argument("--size", type=positive_float, default=1200.0,
                   help="side in metres (default 1200)")
    p.add_argument("--gsd", type=positive_float, default=0.25, help="m/px (default 0.25)")
    p.add_argument("--seed", type=seed_int, default=0)
    p.add_argument("--origin", type=parse_lonlat, help="scene centre lon,lat[,alt]")
    p.add_argument("--keep-sources", help="folder to keep the generated GeoTIFFs in")
    p.add_argument("--force", action="store_true", help="replace an existing package")
    p.set_defaults(handler=run_synth)

    cli_more.add_parsers(tsub)
    sample_data.add_parser(tsub)  # geonav tiles sample-data: the pinned real rasters
    lidar.add_parser(tsub)  # geonav tiles lidar: a LAS/LAZ cloud -> RGB, DSM, DEM


def _report(scene, out: Path) -> None:
    w, h = scene.size_m
    print(f"scene {scene.name}: {scene.width}x{scene.height} px at {scene.gsd_m:g} m/px "
          f"({w:.0f} x {h:.0f} m), origin {scene.origin.lon_deg:.6f},"
          f"{scene.origin.lat_deg:.6f} -> {out}")


def run_ingest(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.tiles.ingest import ingest

    with warnings.catch_warnings():
        warnings.simplefilter("always", GeonavWarning)  # each one, once, as one line
        scene = ingest(args.sources, name=args.name, out=args.out, dsm=args.dsm, dem=args.dem,
                       ground_alt_m=args.ground_alt, gsd_m=args.gsd, origin=args.origin,
                       bbox_lonlat=args.bbox, attribution=args.attribution,
                       overwrite=args.force, compress=args.compress,
                       progress=progress_bar("ingest"), tms=args.tms, zoom=args.zoom,
                       rgb_bands=args.bands, dsm_units=args.dsm_units,
                       memory_budget_mb=args.memory_budget)
    _report(scene, Path(args.out))
    return 0


def run_synth(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.tiles.ingest import ingest_synthetic

    scene = ingest_synthetic(args.kind, out=args.out, name=args.name, size_m=args.size,
                             gsd_m=args.gsd, seed=args.seed, origin=args.origin,
                             overwrite=args.force, keep_sources=args.keep_sources,
                             progress=progress_bar("synth"))
    _report(scene, Path(args.out))
    return 0
