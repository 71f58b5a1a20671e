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

With ``--large-cog`` it instead measures the peak memory (VmHWM of a child
process) of ingesting a large COG (default 16000 x 16000 px RGB at 0.1 m, 768 MB as
an array) without reading it whole: at ``--gsd 0.5`` (read decimated through the
overviews) and at the native GSD cut to a 200 m ``--bbox`` (read by window), next
to the RSS of the imports alone. No gdalwarp needed.

Usage: python bench/bench_ingest.py [--repeat 3] [--keep DIR]
       python bench/bench_ingest.py --large-cog [--cog-px 16000] [--keep DIR]
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


def make_large_cog(path: Path, n: int) -> None:
    """An n x n RGB COG (JPEG, average overviews), written block by block (bounded memory)."""
    import rasterio
    import rasterio.shutil
    from affine import Affine
    from pyproj import Transformer
    from rasterio.windows import Window

    x0, y0 = Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True).transform(8.5, 47.4)
    tmp = path.with_suffix(".tiled.tif")
    rng = np.random.default_rng(2)
    block = 1024
    with rasterio.open(tmp, "w", driver="GTiff", width=n, height=n, count=3, dtype="uint8",
                       crs="EPSG:32632", tiled=True, blockxsize=512, blockysize=512,
                       compress="DEFLATE", BIGTIFF="YES",
                       transform=Affine(0.1, 0, x0 - n * 0.05, 0, -0.1, y0 + n * 0.05)) as d:
        for r in range(0, n, block):
            for c in range(0, n, block):
                h, w = min(block, n - r), min(block, n - c)
                small = rng.integers(0, 255, (max(1, h // 16), max(1, w // 16), 3), np.uint8)
                img = cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)
                d.write(np.moveaxis(img, 2, 0), window=Window(c, r, w, h))
    rasterio.shutil.copy(tmp, path, driver="COG", compress="JPEG", quality=90, blocksize=512,
                         overview_resampling="average", BIGTIFF="YES")
    tmp.unlink()


_CHILD = """
import sys, warnings, json
warnings.simplefilter("ignore")


def vm_hwm_mb():
    # peak RSS of this process image (VmHWM restarts at exec; ru_maxrss would carry the
    # parent's peak over)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024



from geonav.tiles.ingest import ingest
import rasterio, numpy
mode, src, out = sys.argv[1], sys.argv[2], sys.argv[3]
base = vm_hwm_mb()
kw = {}
if mode == "coarse":
    kw = dict(gsd_m=0.5)
elif mode == "bbox":
    with rasterio.open(src) as s:
        from rasterio.warp import transform_bounds
        w, so, e, n = transform_bounds(s.crs, "EPSG:4326", *s.bounds)
    cx, cy = (w + e) / 2, (so + n) / 2
    kw = dict(bbox_lonlat=(cx - 0.0013, cy - 0.0009, cx + 0.0013, cy + 0.0009))
if mode != "imports":
    scene = ingest([src], name="L", out=out, overwrite=True, **kw)
    size = f"{scene.width}x{scene.height} px at {scene.gsd_m:g} m"
else:
    size = "-"
print(json.dumps(dict(mode=mode, peak_mb=vm_hwm_mb(), imports_mb=base, scene=size)))
"""


def bench_large_cog(work: Path, n: int) -> int:
    import json

    cog = work / f"large{n}.tif"
    t0 = time.perf_counter()
    if not cog.exists():
        make_large_cog(cog, n)
    print(f"{n}x{n} px COG ({cog.stat().st_size / 1e6:.0f} MB on disk, "
          f"{n * n * 3 / 2**20:.0f} MiB as an RGB array) ready in {time.perf_counter() - t0:.0f} s")
    print(f"{'case':34s} {'peak RSS MiB':>12s} {'imports MiB':>11s} {'seconds':>8s}  scene")
    for mode, label in (("imports", "imports only"), ("coarse", "whole COG at --gsd 0.5"),
                        ("bbox", "200 m --bbox at native 0.1 m")):
        t0 = time.perf_counter()
        out = subprocess.run([sys.executable, "-c", _CHILD, mode, str(cog), str(work / "scene")],
                             check=True, capture_output=True, text=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        print(f"{label:34s} {r['peak_mb']:12.0f} {r['imports_mb']:11.0f} "
              f"{time.perf_counter() - t0:8.1f}  {r['scene']}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--keep", help="keep the inputs and outputs in this folder")
    parser.add_argument("--large-cog", action="store_true",
                        help="measure the peak memory of ingesting a large COG instead")
    parser.add_argument("--cog-px", type=int, default=16000, help="side of the large COG")
    args = parser.parse_args(argv)
    if args.large_cog:
        work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="geonav-bench-"))
        work.mkdir(parents=True, exist_ok=True)
        try:
            return bench_large_cog(work, args.cog_px)
        finally:
            if not args.keep:
                shutil.rmtree(work, ignore_errors=True)
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
