"""Ingestion throughput: geonav vs ``gdalwarp`` doing the same reprojection, same run.

Two inputs, built in a temporary folder:

* a 4000 x 4000 px RGB GeoTIFF (UTM 32N, 0.25 m, tiled, uncompressed);
* a 400-tile XYZ folder (20 x 20 JPEG tiles at zoom 19, 5120 x 5120 px).

For each, geonav's :func:`geonav.tiles.ingest.ingest` (read, plan the grid, reproject
with the mask as alpha, write the COG package) is timed against ``gdalwarp`` onto the
identical grid (the local tmerc, same GSD, bounds and resampling, alpha band, 2 threads):

* ``reproject``: geonav read + reproject stages vs ``gdalwarp`` to an uncompressed GTiff;
* ``package``: the whole ``ingest()`` vs ``gdalwarp -of COG`` with JPEG q92, 512 blocks,
  average overviews (what the package's ortho.tif holds).

GDAL reads the XYZ folder through its WMS/TMS driver with a ``file://`` template.
Throughput is source megapixels per second; medians of ``--repeat`` runs.

Usage: python bench/bench_ingest.py [--repeat 3] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import cv2
import numpy as np


def make_geotiff(path: Path, n: int = 4000) -> None:
    import rasterio
    from affine import Affine
    from pyproj import Transformer

    x0, y0 = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True).transform(8.5, 47.4)
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 255, (n // 8, n // 8, 3), dtype=np.uint8), (n, n),
                      interpolation=cv2.INTER_CUBIC)
    noise = rng.integers(0, 40, (n, n, 3), dtype=np.uint8)
    img = cv2.add(base, noise)
    with rasterio.open(path, "w", driver="GTiff", width=n, height=n, count=3, dtype="uint8",
                       crs="EPSG:32632", tiled=True, blockxsize=512, blockysize=512,
                       transform=Affine(0.25, 0, x0 - n * 0.125, 0, -0.25, y0 + n * 0.125)) as d:
        d.write(np.moveaxis(img, 2, 0))


def make_xyz(folder: Path, side: int = 20, z: int = 19) -> None:
    from geonav.tiles.xyz import web_mercator_tms

    t = web_mercator_tms().tile(8.5, 47.4, z)
    rng = np.random.default_rng(1)
    for dx in range(side):
        for dy in range(side):
            img = cv2.add(cv2.resize(rng.integers(0, 255, (32, 32, 3), dtype=np.uint8),
                                     (256, 256), interpolation=cv2.INTER_CUBIC),
                          rng.integers(0, 40, (256, 256, 3), dtype=np.uint8))
            p = folder / str(z) / str(t.x + dx) / f"{t.y + dy}.jpg"
            p.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(p), img, [cv2.IMWRITE_JPEG_QUALITY, 90])


def wms_xml(folder: Path, z: int, out: Path) -> Path:
    out.write_text(f"""<GDAL_WMS>
  <Service name="TMS"><ServerUrl>file://{folder.resolve()}/${{z}}/${{x}}/${{y}}.jpg</ServerUrl>
  </Service>
  <DataWindow><UpperLeftX>-20037508.342789244</UpperLeftX>
  <UpperLeftY>20037508.342789244</UpperLeftY><LowerRightX>20037508.342789244</LowerRightX>
  <LowerRightY>-20037508.342789244</LowerRightY><TileLevel>{z}</TileLevel>
  <TileCountX>1</TileCountX><TileCountY>1</TileCountY><YOrigin>top</YOrigin></DataWindow>
  <Projection>EPSG:3857</Projection><BlockSizeX>256</BlockSizeX><BlockSizeY>256</BlockSizeY>
  <BandsCount>3</BandsCount><ZeroBlockHttpCodes>204,404</ZeroBlockHttpCodes>
</GDAL_WMS>
""")
    return out


def timed(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_one(label: str, source: Path, gdal_source: Path, src_mpix: float, work: Path,
              repeat: int, **ingest_kw) -> list[tuple[str, float, float, float]]:
    from geonav.tiles.ingest import ingest, open_source, plan_grid, reproject_rgb

    def geonav_reproject():
        src = open_source(source)
        grid = plan_grid([src])
        reproject_rgb([src], grid)
        return grid

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        grid = geonav_reproject()
        _, _, method = reproject_rgb([open_source(source)], grid)
        t_reproject = timed(geonav_reproject, repeat)
        t_package = timed(lambda: ingest([source], name="b", out=work / f"{label}-scene",
                                         overwrite=True, **ingest_kw), repeat)
    crs = grid.crs.to_wkt()
    (work / "dst.wkt").write_text(crs)
    t = grid.transform
    te = [t.c, t.f - grid.height * grid.gsd_m, t.c + grid.width * grid.gsd_m, t.f]
    resampling = "average" if "average" in method else "bilinear"
    common = ["gdalwarp", "-q", "-overwrite", "-t_srs", str(work / "dst.wkt"),
              "-tr", repr(grid.gsd_m), repr(grid.gsd_m), "-te", *map(repr, te),
              "-r", resampling, "-dstalpha", "-multi", "-wo", "NUM_THREADS=2",
              "--config", "GDAL_NUM_THREADS", "2", "--config", "GDAL_CACHEMAX", "512"]

    def gdal(args):
        subprocess.run(common + args, check=True, capture_output=True)

    g_reproject = timed(lambda: gdal([str(gdal_source), str(work / "g.tif")]), repeat)
    g_package = timed(lambda: gdal(["-of", "COG", "-co", "COMPRESS=JPEG", "-co", "QUALITY=92",
                                    "-co", "BLOCKSIZE=512", "-co", "OVERVIEW_RESAMPLING=AVERAGE",
                                    str(gdal_source), str(work / "g_cog.tif")]), repeat)
    return [(f"{label} reproject ({resampling})", src_mpix, t_reproject, g_reproject),
            (f"{label} package (COG JPEG)", src_mpix, t_package, g_package)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--keep", help="keep the inputs and outputs in this folder")
    args = parser.parse_args(argv)
    if shutil.which("gdalwarp") is None:
        print("gdalwarp not found: apt-get install gdal-bin", file=sys.stderr)
        return 1
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="geonav-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        tif, xyz = work / "src4000.tif", work / "xyz400"
        t0 = time.perf_counter()
        if not tif.exists():
            make_geotiff(tif)
        if not xyz.exists():
            make_xyz(xyz)
        print(f"inputs ready in {time.perf_counter() - t0:.1f} s under {work}")
        rows = bench_one("GeoTIFF 4000x4000", tif, tif, 16.0, work, args.repeat)
        rows += bench_one("XYZ 400 tiles", xyz, wms_xml(xyz, 19, work / "xyz.xml"),
                          400 * 256 * 256 / 1e6, work, args.repeat)
        print(f"\nmedian of {args.repeat} runs, source MPix/s (2 threads each)")
        print(f"{'case':36s} {'geonav s':>9s} {'MPix/s':>7s} {'gdalwarp s':>10s} "
              f"{'MPix/s':>7s} {'ratio':>6s}")
        worst = 0.0
        for name, mpix, tg, tw in rows:
            ratio = tg / tw
            worst = max(worst, ratio)
            print(f"{name:36s} {tg:9.2f} {mpix / tg:7.1f} {tw:10.2f} {mpix / tw:7.1f} "
                  f"{ratio:5.2f}x")
        print(f"\nworst geonav/gdalwarp time ratio {worst:.2f}x (target <= 1.5x): "
              f"{'met' if worst <= 1.5 else 'NOT met'}")
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
