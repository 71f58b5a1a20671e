"""``geonav tiles fetch|info|preview``: download tiles, summarise and draw scenes."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from geonav.cliutil import nonneg_int, positive_float, positive_floats, positive_int
from geonav.tiles.cli_helpers import parse_bbox, parse_subdomains


def add_parsers(tsub: argparse._SubParsersAction) -> None:
    p = tsub.add_parser(
        "fetch", help="download XYZ tiles for a lon/lat bbox from a URL template into a cache",
        description="Download the XYZ tiles of a bbox at one zoom from a tile server you may "
        "use, into a resumable {z}/{x}/{y} cache that 'geonav tiles ingest' reads. No provider "
        "is built in; check the provider's terms (many forbid offline use or machine analysis).")
    p.add_argument("url", help="URL template with {z} {x} {y} (or {-y} for TMS rows, {q} for "
                   "a Bing quadkey, {s} for a subdomain), e.g. 'https://tiles.example/{z}/{x}/{y}"
                   ".png'; quote it")
    p.add_argument("--bbox", type=parse_bbox, required=True,
                   help="west,south,east,north in degrees")
    p.add_argument("--zoom", type=nonneg_int, required=True, help="zoom level (0..24)")
    p.add_argument("--out", required=True, help="cache folder (tiles land in OUT/z/x/y.ext)")
    p.add_argument("--attribution", required=True,
                   help="provider and licence/terms under which you may use these tiles; "
                   "stored with the tiles and in the scene manifest")
    p.add_argument("--max-tiles", type=positive_int, default=2000,
                   help="refuse when the bbox needs more tiles (default 2000)")
    p.add_argument("--workers", type=positive_int, default=4,
                   help="concurrent requests (default 4)")
    p.add_argument("--subdomains", default="abc",
                   help="values for {s}: letters ('abc') or comma-separated names")
    p.add_argument("--user-agent", help="User-Agent header (default: geonav/<version> ...)")
    p.add_argument("--timeout", type=positive_float, default=20.0,
                   help="seconds per request: connect, each read and the whole body")
    p.add_argument("--retries", type=nonneg_int, default=4,
                   help="retries per tile on 429/5xx/timeouts (default 4)")
    p.add_argument("--retry-missing", action="store_true",
                   help="ask again for tiles an earlier run found missing (404)")
    p.add_argument("--verify", action="store_true",
                   help="decode the tiles already cached for the bbox; bad ones are deleted "
                   "and fetched again")
    p.set_defaults(handler=run_fetch)

    p = tsub.add_parser("info", help="summarise a scene package")
    p.add_argument("scene", help="scene package folder")
    p.add_argument("--obs-size", type=positive_int, default=84, help="camera image size in px (84)")
    p.add_argument("--fov", type=positive_float, default=90.0, help="camera field of view, degrees")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--verify", action="store_true",
                   help="check every raster against its sha256 in scene.json (reads them all; "
                   "without it, a raster is checked only when it is decoded anew)")
    p.set_defaults(handler=run_info)

    p = tsub.add_parser("preview", help="draw a scene with tasks and camera footprints to a PNG")
    p.add_argument("scene", help="scene package folder")
    p.add_argument("--tasks", help="task set JSON to draw (regions and targets)")
    p.add_argument("-o", "--out", required=True, help="PNG to write")
    p.add_argument("--alts", type=positive_floats, default=(300.0, 75.0, 45.0, 15.0),
                   help="altitudes whose footprints are drawn (default 300,75,45,15)")
    p.add_argument("--max-px", type=positive_int, default=1600, help="image pixels across (1600)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing picture (only one geonav drew)")
    p.set_defaults(handler=run_preview)


def run_fetch(args: argparse.Namespace) -> int:
    from geonav.cliutil import progress_bar
    from geonav.tiles.fetch import USER_AGENT, FetchIncomplete, fetch_tiles

    try:
        result = fetch_tiles(
            args.url, args.bbox, args.zoom, args.out, attribution=args.attribution,
            max_tiles=args.max_tiles, workers=args.workers,
            subdomains=parse_subdomains(args.subdomains), user_agent=args.user_agent or USER_AGENT,
            timeout_s=args.timeout, retries=args.retries, retry_not_found=args.retry_missing,
            verify=args.verify, progress=progress_bar("fetch"))
    except FetchIncomplete as err:
        r = err.result
        print(f"fetched {r.downloaded}, cached {r.cached}, missing (404) {r.not_found}, "
              f"FAILED {r.failed} of {r.total} tiles at zoom {r.zoom} -> {r.folder}")
        for line in r.failures:
            print(f"  {line}")
        raise
    if args.verify:
        print(f"verified {result.verified} cached tiles: {result.invalid_removed} were bad, "
              "deleted and fetched again")
    print(f"{result.total} tiles at zoom {result.zoom}: {result.downloaded} downloaded "
          f"({result.bytes / 1e6:.1f} MB, {result.retries} retries), {result.cached} already "
          f"cached, {result.not_found} missing on the server (404, masked) -> {result.folder}")
    print(f"next: geonav tiles ingest {result.folder} --zoom {result.zoom} --name NAME "
          "--out SCENE")
    return 0


def run_info(args: argparse.Namespace) -> int:
    from geonav.camera import Camera
    from geonav.scene import Scene
    from geonav.tiles.info import format_summary, summarize

    scene = Scene.open(args.scene, verify_checksums=args.verify)
    summary = summarize(scene, camera=Camera(size_px=args.obs_size, fov_deg=args.fov))
    if args.json:
        json.dump(summary, sys.stdout, indent=2)
        print()
    else:
        print(format_summary(summary))
    return 0


def run_preview(args: argparse.Namespace) -> int:
    from geonav.outputs import check_replaceable, not_a_geonav_picture, output_lock

    with output_lock(args.out, "-o"):
        check_replaceable(args.out, "picture", force=args.force, why_not=not_a_geonav_picture)
        return _preview(args)


def _preview(args: argparse.Namespace) -> int:
    from geonav.scene import Scene
    from geonav.tasks import TaskSet
    from geonav.viz import draw_scene

    alts = tuple(args.alts)
    scene = Scene.open(args.scene)
    tasks = None
    title = None
    chance = ""
    if args.tasks:
        from geonav.difficulty import describe, taskset_difficulty

        tasks = TaskSet.load(args.tasks)
        tasks.check_scene(scene)
        diff = tasks.meta.get("difficulty") if isinstance(tasks.meta, dict) else None
        if not isinstance(diff, dict) or "blind_sr" not in diff:
            diff = taskset_difficulty(tasks, scene)
        chance = f"; chance: {describe(diff)}"
        title = (f"{scene.name}: {len(tasks)} tasks; random walk SR "
                 f"{diff['random_walk_sr']:.2f}, best view-blind {diff['blind_sr']:.2f}")
    out = draw_scene(scene, args.out, tasks=tasks, footprints_at=alts, max_px=args.max_px,
                     title=title)
    n = len(tasks) if tasks is not None else 0
    print(f"wrote {Path(out)} (scene {scene.name}, {n} tasks, footprints at "
          f"{', '.join(f'{a:g}' for a in alts)} m{chance})")
    return 0
