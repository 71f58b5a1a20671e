"""Scenes: an orthophoto on the scene grid, its mask, an optional DSM and a manifest.

A scene package on disk (DESIGN.md "Scene package") is a folder holding
``ortho.tif`` (COG, RGB uint8, internal mask, north-up, square pixels, in the
local tmerc scene CRS), an optional ``dsm.tif`` (float32 metres of surface
height above the ground, same grid, NaN where unknown) and ``scene.json``.
:meth:`Scene.open` validates all of it and names exactly what is wrong.
Packages are written into a temporary folder beside the target and renamed
into place only when complete.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import tempfile
import uuid
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geonav import __version__
from geonav.errors import SceneError
from geonav.geo import LonLat, SceneFrame, ScenePoint, parse_crs, scene_crs

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
MANIFEST = "scene.json"
ORTHO = "ortho.tif"
DSM = "dsm.tif"
DSM_HEIGHT_REFERENCE = "height above ground (m)"


def sha256_file(path: str | os.PathLike[str], chunk: int = 1 << 20) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


@dataclass
class Scene:
    """An orthophoto scene on a north-up grid in the local tmerc scene CRS.

    Attributes:
        name: short scene name ("A", "B", ...).
        rgb: (H, W, 3) uint8 image, row 0 at the north edge.
        mask: (H, W) bool, True where the imagery is valid.
        gsd_m: ground sample distance in metres per pixel (square pixels).
        transform: affine pixel -> scene CRS metres (upper-left corner convention).
        origin: the scene origin (CRS centre); ``alt_m`` is the ground AMSL there.
        dsm: (H, W) float32 surface height above the ground in metres, or None.
        manifest: the ``scene.json`` content (sources, attribution, ...).
        path: the package folder when opened from disk.
    """

    name: str
    rgb: np.ndarray
    mask: np.ndarray
    gsd_m: float
    transform: Affine
    origin: LonLat
    dsm: np.ndarray | None = None
    manifest: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def __post_init__(self) -> None:
        if self.rgb.ndim != 3 or self.rgb.shape[2] != 3 or self.rgb.dtype != np.uint8:
            raise SceneError(f"scene {self.name!r}: rgb must be (H, W, 3) uint8, got "
                             f"{self.rgb.shape} {self.rgb.dtype}")
        if self.mask.shape != self.rgb.shape[:2]:
            raise SceneError(f"scene {self.name!r}: mask shape {self.mask.shape} != image "
                             f"{self.rgb.shape[:2]}")
        if self.dsm is not None and self.dsm.shape != self.rgb.shape[:2]:
            raise SceneError(f"scene {self.name!r}: DSM shape {self.dsm.shape} != image "
                             f"{self.rgb.shape[:2]}")
        if not (self.gsd_m > 0 and math.isfinite(self.gsd_m)):
            raise SceneError(f"scene {self.name!r}: gsd_m must be positive, got {self.gsd_m}")
        self.frame = SceneFrame(self.origin)

    # -- construction -----------------------------------------------------------------
    @classmethod
    def from_arrays(
        cls,
        name: str,
        rgb: np.ndarray,
        origin: LonLat,
        gsd_m: float,
        dsm: np.ndarray | None = None,
        mask: np.ndarray | None = None,
    ) -> Scene:
        """An in-memory scene whose centre is ``origin`` (tests, synthetic data)."""
        height, width = rgb.shape[:2]
        transform = Affine(gsd_m, 0.0, -width * gsd_m / 2, 0.0, -gsd_m, height * gsd_m / 2)
        if mask is None:
            mask = np.ones((height, width), dtype=bool)
        return cls(name, np.ascontiguousarray(rgb), mask.astype(bool), float(gsd_m),
                   transform, origin, None if dsm is None else dsm.astype(np.float32))

    # -- geometry ---------------------------------------------------------------------
    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def crs_wkt(self) -> str:
        return self.frame.crs.to_wkt()

    @property
    def bounds_m(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) in scene metres."""
        t = self.transform
        return (t.c, t.f - self.height * self.gsd_m, t.c + self.width * self.gsd_m, t.f)

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) in metres."""
        return self.width * self.gsd_m, self.height * self.gsd_m

    def to_pixel(self, x_m: float, y_m: float) -> tuple[float, float]:
        """Scene metres -> fractional (col, row) of the pixel grid (0, 0 = UL corner)."""
        return (x_m - self.transform.c) / self.gsd_m, (self.transform.f - y_m) / self.gsd_m

    def window(self, region_m: tuple[float, float, float, float]) -> tuple[slice, slice]:
        """Row and column slices of the pixels whose centres lie inside ``region_m``."""
        xmin, ymin, xmax, ymax = region_m
        c0, r0 = self.to_pixel(xmin, ymax)
        c1, r1 = self.to_pixel(xmax, ymin)
        rs = slice(max(0, math.ceil(r0 - 0.5)), min(self.height, math.ceil(r1 - 0.5)))
        cs = slice(max(0, math.ceil(c0 - 0.5)), min(self.width, math.ceil(c1 - 0.5)))
        return rs, cs

    @property
    def scene_id(self) -> str:
        """A short fingerprint of the scene (name, grid and origin) for task files."""
        key = json.dumps([self.name, self.width, self.height, round(self.gsd_m, 6),
                          list(self.transform)[:6], self.origin.lon_deg, self.origin.lat_deg])
        return hashlib.sha256(key.encode()).hexdigest()[:16]

    # -- copies and pickles -----------------------------------------------------------
    def is_mapped(self) -> bool:
        """True when the rasters are still the package's read-only memory maps from :meth:`open`.

        Such a scene pickles as its package path (a few hundred bytes): the receiving
        process maps the same decoded rasters (:func:`open_shared`) instead of getting a
        copy of them.
        """
        mapped = self.__dict__.get("_mapped")
        if mapped is None or self.path is None:
            return False
        now = (self.rgb, self.mask, self.dsm)
        return all(a is b for a, b in zip(now, mapped, strict=True))

    def __getstate__(self) -> dict[str, Any]:
        # caches (render maps, renderers) are rebuilt where the scene lands
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_")}

    def __reduce_ex__(self, protocol: Any) -> Any:
        if self.is_mapped():
            return (open_shared, (str(self.path),))
        return super().__reduce_ex__(protocol)

    def __copy__(self) -> Scene:
        new = object.__new__(type(self))
        new.__dict__.update({k: v for k, v in self.__dict__.items() if not k.startswith("_")
                             or k == "_mapped"})
        return new

    def __deepcopy__(self, memo: dict[int, Any]) -> Scene:
        import copy

        new = object.__new__(type(self))
        memo[id(self)] = new
        new.__dict__.update(copy.deepcopy({k: v for k, v in self.__dict__.items()
                                           if not k.startswith("_")}, memo))
        return new

    # -- disk -------------------------------------------------------------------------
    def save(self, out_dir: str | os.PathLike[str], *, overwrite: bool = False,
             compress: str = "JPEG") -> Path:
        """Write the scene package atomically (temp folder, then rename).

        Args:
            out_dir: the package folder to create.
            overwrite: replace an existing package at ``out_dir``.
            compress: ortho compression: "JPEG" (quality 92, small) or "DEFLATE" (lossless).
        """
        import rasterio

        out = Path(out_dir)
        if out.exists() and not overwrite:
            raise SceneError(f"{out} exists; pass overwrite=True (CLI: --force) to replace it")
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
        tmp.chmod(0o755)
        try:
            crs = self.frame.crs.to_wkt()
            profile: dict[str, Any] = dict(
                driver="COG", width=self.width, height=self.height, transform=self.transform,
                crs=crs, blocksize=512, overview_resampling="average", BIGTIFF="IF_SAFER",
            )
            rgb_opts = dict(compress=compress, quality=92) if compress.upper() == "JPEG" else \
                dict(compress=compress, predictor=2)
            with rasterio.open(tmp / ORTHO, "w", count=3, dtype="uint8", **profile,
                               **rgb_opts) as dst:
                dst.write(np.moveaxis(self.rgb, 2, 0))
                dst.write_mask(self.mask.astype(np.uint8) * 255)
            if self.dsm is not None:
                with rasterio.open(tmp / DSM, "w", count=1, dtype="float32", nodata=float("nan"),
                                   compress="DEFLATE", predictor=3, **profile) as dst:
                    dst.write(self.dsm.astype(np.float32), 1)
            manifest = self._manifest(tmp)
            (tmp / MANIFEST).write_text(json.dumps(manifest, indent=2))
            if out.exists():
                shutil.rmtree(out)
            os.replace(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        self.manifest, self.path = manifest, out
        self.__dict__.pop("_mapped", None)  # the arrays are not the new package's decoding
        log.info("wrote scene %s to %s (%dx%d px at %.3f m)", self.name, out, self.width,
                 self.height, self.gsd_m)
        return out

    def _manifest(self, folder: Path) -> dict[str, Any]:
        xmin, ymin, xmax, ymax = self.bounds_m
        corners = [self.frame.to_lonlat(ScenePoint(x, y)) for x in (xmin, xmax) for y in (ymin, ymax)]
        manifest = dict(self.manifest)
        manifest.update(
            schema_version=SCHEMA_VERSION,
            name=self.name,
            crs_wkt2=self.frame.crs.to_wkt(),
            gsd_m=self.gsd_m,
            transform=list(self.transform)[:6],
            width=self.width,
            height=self.height,
            bounds_m=[xmin, ymin, xmax, ymax],
            bounds_wgs84=[min(c.lon_deg for c in corners), min(c.lat_deg for c in corners),
                          max(c.lon_deg for c in corners), max(c.lat_deg for c in corners)],
            origin=dict(lon_deg=self.origin.lon_deg, lat_deg=self.origin.lat_deg,
                        alt_m=self.origin.alt_m, alt_reference="AMSL (ground at origin)"),
            frame="local tmerc: +x east, +y north; NED north = y, east = x",
            ortho=dict(file=ORTHO, sha256=sha256_file(folder / ORTHO)),
            dsm=None if self.dsm is None else dict(
                file=DSM, sha256=sha256_file(folder / DSM),
                height_reference=DSM_HEIGHT_REFERENCE),
            geonav_version=__version__,
        )
        manifest.setdefault("sources", [])
        manifest.setdefault("attribution", "")
        return manifest

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, verify_checksums: bool = False) -> Scene:
        """Open and validate a scene package; SceneError names each problem found."""
        import rasterio
        from rasterio.errors import RasterioError

        folder = Path(path)
        if not folder.is_dir():
            raise SceneError(f"scene package {folder} does not exist or is not a folder; "
                             "create one with 'geonav tiles ingest' or 'geonav tiles synth'")
        manifest = read_manifest(folder)
        problems: list[str] = []
        ortho_path = folder / manifest["ortho"]["file"]
        if not ortho_path.is_file():
            raise SceneError(f"{folder}: {ortho_path.name} is missing")
        if verify_checksums and sha256_file(ortho_path) != manifest["ortho"]["sha256"]:
            problems.append(f"{ortho_path.name} does not match its sha256 in {MANIFEST}")
        origin = LonLat(**{k: manifest["origin"][k] for k in ("lon_deg", "lat_deg", "alt_m")})
        try:
            with rasterio.open(ortho_path) as src:
                if src.count != 3 or src.dtypes[0] != "uint8":
                    problems.append(f"{ortho_path.name} must be 3-band uint8, has {src.count} "
                                    f"band(s) of {src.dtypes[0]}")
                if (src.width, src.height) != (manifest["width"], manifest["height"]):
                    problems.append(f"{ortho_path.name} is {src.width}x{src.height} px but "
                                    f"{MANIFEST} says {manifest['width']}x{manifest['height']}")
                if not np.allclose(list(src.transform)[:6], manifest["transform"], atol=1e-6):
                    problems.append(f"{ortho_path.name} transform {list(src.transform)[:6]} "
                                    f"!= {MANIFEST} transform {manifest['transform']}")
                if src.crs is None:
                    problems.append(f"{ortho_path.name} has no CRS")
                elif not parse_crs(src.crs.to_wkt()).equals(parse_crs(manifest["crs_wkt2"])):
                    problems.append(f"{ortho_path.name} CRS differs from {MANIFEST} crs_wkt2")
                if problems:
                    raise SceneError(f"scene package {folder} is inconsistent: "
                                     + "; ".join(problems))
                rgb, mask = mapped_ortho(ortho_path, src)
            dsm = None
            if manifest.get("dsm"):
                dsm_path = folder / manifest["dsm"]["file"]
                if not dsm_path.is_file():
                    raise SceneError(f"{folder}: {MANIFEST} lists a DSM but {dsm_path.name} "
                                     "is missing")
                with rasterio.open(dsm_path) as src:
                    if (src.width, src.height) != (manifest["width"], manifest["height"]):
                        raise SceneError(f"{dsm_path.name} is {src.width}x{src.height} px, "
                                         f"not on the ortho grid "
                                         f"{manifest['width']}x{manifest['height']}")
                    dsm = mapped_dsm(dsm_path, src)
        except RasterioError as err:
            raise SceneError(f"cannot read the rasters of {folder}: {err}") from err
        expected = scene_crs(origin)
        if not parse_crs(manifest["crs_wkt2"]).equals(expected):
            log.warning("scene %s: CRS is not the local tmerc at its origin", folder)
        transform = Affine(*manifest["transform"])
        if not math.isclose(transform.a, -transform.e, rel_tol=1e-9) or transform.b or transform.d:
            raise SceneError(f"scene {folder}: pixels must be square and north-up, transform "
                             f"is {manifest['transform']}")
        scene = cls(manifest["name"], rgb, mask, float(manifest["gsd_m"]), transform, origin,
                    dsm, manifest, folder)
        scene.__dict__["_mapped"] = (rgb, mask, dsm)
        return scene


_REQUIRED: dict[str, type | tuple[type, ...]] = {
    "schema_version": int, "name": str, "crs_wkt2": str, "gsd_m": (int, float),
    "transform": list, "width": int, "height": int, "bounds_m": list, "bounds_wgs84": list,
    "origin": dict, "ortho": dict, "sources": list,
}


def read_manifest(folder: Path) -> dict[str, Any]:
    """Read and check ``scene.json``; SceneError lists every missing or mistyped field."""
    path = folder / MANIFEST
    if not path.is_file():
        raise SceneError(f"{folder} has no {MANIFEST}; is it a scene package?")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SceneError(f"{path} is not valid JSON ({err}); re-create the package") from err
    if not isinstance(manifest, dict):
        raise SceneError(f"{path} must hold a JSON object")
    problems = []
    for key, typ in _REQUIRED.items():
        if key not in manifest:
            problems.append(f"missing {key!r}")
        elif not isinstance(manifest[key], typ) or isinstance(manifest[key], bool):
            problems.append(f"{key!r} has the wrong type ({type(manifest[key]).__name__})")
    if not problems:
        if manifest["schema_version"] != SCHEMA_VERSION:
            problems.append(f"schema_version {manifest['schema_version']} is not "
                            f"{SCHEMA_VERSION}; re-ingest with this geonav")
        if len(manifest["transform"]) != 6:
            problems.append("'transform' must have 6 coefficients")
        if manifest["gsd_m"] <= 0:
            problems.append(f"'gsd_m' must be positive, is {manifest['gsd_m']}")
        if manifest["width"] <= 0 or manifest["height"] <= 0:
            problems.append("'width' and 'height' must be positive")
        for key in ("lon_deg", "lat_deg", "alt_m"):
            if not isinstance(manifest["origin"].get(key), (int, float)):
                problems.append(f"'origin.{key}' is missing or not a number")
        if "file" not in manifest["ortho"]:
            problems.append("'ortho.file' is missing")
        try:
            parse_crs(manifest["crs_wkt2"])
        except Exception as err:  # noqa: BLE001 - reported as a problem below
            problems.append(f"'crs_wkt2' is not a valid CRS ({err})")
    if problems:
        raise SceneError(f"{path} is invalid: " + "; ".join(problems))
    return manifest


# -- memory-mapped rasters (the loading side of Scene.open) --------------------------------
CACHE_ENV = "GEONAV_CACHE_DIR"
"""Environment variable: the folder for decoded rasters of every package (default: a
``.geonav-cache`` folder inside each package, or ``$XDG_CACHE_HOME/geonav`` when the
package is read-only). ``GEONAV_RASTER_CACHE=0`` turns the cache off: rasters are then
decoded into each process's memory, as before (more memory per worker, no disk used)."""
PACKAGE_CACHE = ".geonav-cache"


def raster_cache_dir(folder: Path) -> Path:
    """The folder that holds a package's decoded rasters (created if needed)."""
    override = os.environ.get(CACHE_ENV)
    if not override:
        local = folder / PACKAGE_CACHE
        try:
            local.mkdir(exist_ok=True)
            if os.access(local, os.W_OK):
                return local
        except OSError:
            pass
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "geonav"
    else:
        base = Path(override)
    sub = base / "scenes" / hashlib.sha256(str(folder.resolve()).encode()).hexdigest()[:16]
    sub.mkdir(parents=True, exist_ok=True)
    return sub


def file_key(path: Path) -> str:
    """A short key that changes whenever the file at ``path`` is replaced or rewritten."""
    st = path.stat()
    return hashlib.sha256(f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode()
                          ).hexdigest()[:16]


def cached_array(path: Path, build: Callable[[], np.ndarray]) -> np.ndarray:
    """A read-only memory map of the ``.npy`` file at ``path``, written first from ``build()``.

    The file is written to a temporary name and renamed, so processes that race on it
    all map a whole file; older files of the same name stem with another key (the last
    ``-`` part) are removed. When the folder cannot be written, the built array is
    returned (read-only, in memory) and a warning logged.

    Memory-mapped pages belong to the page cache: every process that maps the same
    file shares them, which is what keeps vector-env workers light.
    """
    if os.environ.get("GEONAV_RASTER_CACHE") == "0":
        arr = np.ascontiguousarray(build())
        arr.flags.writeable = False
        return arr
    if path.is_file():
        try:
            return np.asarray(np.load(path, mmap_mode="r"))
        except (OSError, ValueError) as err:  # truncated by a crash before the rename
            log.warning("rebuilding the unreadable raster cache %s (%s)", path, err)
    arr = np.ascontiguousarray(build())
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    try:
        with open(tmp, "wb") as f:
            np.save(f, arr)
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        log.warning("cannot write the raster cache %s (%s); keeping it in memory", path, err)
        arr.flags.writeable = False
        return arr
    stem = path.name.rsplit("-", 1)[0]
    for old in path.parent.glob(f"{stem}-*.npy"):
        if old != path and old.name.rsplit("-", 1)[0] == stem:
            old.unlink(missing_ok=True)
    return np.asarray(np.load(path, mmap_mode="r"))


def mapped_ortho(path: Path, src: Any) -> tuple[np.ndarray, np.ndarray]:
    """The ortho's (H, W, 3) uint8 pixels and (H, W) bool mask as read-only memory maps.

    Decoded from the open dataset ``src`` on first use into the package's raster cache
    (:func:`raster_cache_dir`); later opens, in any process, only map the files.
    """
    cache, key = raster_cache_dir(path.parent), file_key(path)
    rgb = cached_array(cache / f"{path.stem}.rgb-{key}.npy",
                       lambda: np.moveaxis(src.read(), 0, 2))
    mask = cached_array(cache / f"{path.stem}.mask-{key}.npy", lambda: src.dataset_mask() > 0)
    return rgb, mask


def mapped_dsm(path: Path, src: Any) -> np.ndarray:
    """The DSM's (H, W) float32 metres as a read-only memory map (see :func:`mapped_ortho`)."""
    cache, key = raster_cache_dir(path.parent), file_key(path)
    return cached_array(cache / f"{path.stem}.dsm-{key}.npy",
                        lambda: src.read(1).astype(np.float32))


_SHARED: weakref.WeakValueDictionary[tuple[str, int], Scene] = weakref.WeakValueDictionary()


def open_shared(path: str | os.PathLike[str]) -> Scene:
    """The process's :class:`Scene` of a package: opened once, shared while anyone holds it.

    Envs of one process that name the same package (or are unpickled from one) share
    one scene object, hence one set of render maps (:class:`geonav.camera.SliceRenderer`).
    The scene is re-opened when its ``scene.json`` has changed since.
    """
    folder = Path(path)
    try:
        stamp = (folder / MANIFEST).stat().st_mtime_ns
    except OSError:
        stamp = -1
    key = (str(folder.resolve()), stamp)
    scene = _SHARED.get(key)
    if scene is None:
        scene = Scene.open(folder)
        _SHARED[key] = scene
    return scene
