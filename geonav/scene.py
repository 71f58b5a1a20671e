"""Scenes: an orthophoto on the scene grid, its mask, an optional DSM and a manifest.

A scene package on disk (DESIGN.md "Scene package") is a folder holding
``ortho.tif`` (COG, RGB uint8, internal mask, north-up, square pixels, in the
local tmerc scene CRS), an optional ``dsm.tif`` (float32 metres of surface
height above the ground, same grid, NaN where unknown) and ``scene.json``.
:meth:`Scene.open` validates all of it and names exactly what is wrong.
Packages are written into a temporary folder beside the target and renamed
into place only when complete.

This module owns :class:`Scene` (the arrays, grid, frame and its load and save) and
:func:`open_shared`. The package's file names, manifest checks, checksums and temp
folders live in :mod:`geonav.scene_package`, the decoded-raster memory maps in
:mod:`geonav.raster_cache`; their public names are re-exported here.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geonav import __version__
from geonav.errors import GeonavError, SceneError
from geonav.geo import LonLat, SceneFrame, parse_crs
from geonav.raster_cache import (
    CACHE_ENV,
    PACKAGE_CACHE,
    cached_array,
    file_key,
    mapped_dsm,
    mapped_ortho,
    raster_cache_dir,
)
from geonav.scene_package import (
    BOUNDS_TOL_DEG,
    BOUNDS_TOL_M,
    DSM,
    DSM_HEIGHT_REFERENCE,
    MANIFEST,
    ORIGIN_TOL_M,
    ORTHO,
    SCHEMA_VERSION,
    check_bounds,
    check_origin,
    checksum_problems,
    clean_stale_temps,
    grid_bounds_wgs84,
    read_manifest,
    sha256_file,
    temp_dir,
    verify_sha256,
)

__all__ = [
    "BOUNDS_TOL_DEG", "BOUNDS_TOL_M", "CACHE_ENV", "DSM", "DSM_HEIGHT_REFERENCE", "MANIFEST",
    "ORIGIN_TOL_M", "ORTHO", "PACKAGE_CACHE", "SCHEMA_VERSION", "Scene", "cached_array",
    "clean_stale_temps", "file_key", "grid_bounds_wgs84", "mapped_dsm", "mapped_ortho",
    "open_shared", "raster_cache_dir", "read_manifest", "sha256_file", "temp_dir",
    "verify_sha256",
]

log = logging.getLogger(__name__)


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

    @property
    def identity(self) -> str:
        """A short content hash of the scene (name, grid, a strided sample of the pixels
        and of the DSM): what names it in caches shared by several envs. Unlike
        :attr:`scene_id` (the grid only) it tells apart two scenes on the same grid.
        Computed once."""
        ident = self.__dict__.get("_identity")
        if ident is None:
            h = hashlib.sha256()
            h.update(json.dumps([self.name, list(self.rgb.shape), list(self.transform)[:6],
                                 self.gsd_m]).encode())
            stride = max(1, int(math.sqrt(self.rgb.shape[0] * self.rgb.shape[1] / 250_000)))
            h.update(np.ascontiguousarray(self.rgb[::stride, ::stride]).tobytes())
            if self.dsm is not None:
                h.update(np.ascontiguousarray(self.dsm[::stride, ::stride]).tobytes())
            ident = self.__dict__["_identity"] = h.hexdigest()[:16]
        return ident

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
        """Write the scene package atomically (temp folder, then rename), under the lock of
        ``out_dir`` (:func:`geonav.outputs.output_lock`).

        Raises:
            SceneError: ``out_dir`` exists and may not be replaced, or cannot be written.
            OutputBusy: another process is writing ``out_dir``.

        Args:
            out_dir: the package folder to create.
            overwrite: replace an existing package at ``out_dir`` (only a scene package,
                holding only the files geonav writes into one; anything else is refused).
            compress: ortho compression: "JPEG" (quality 92, small) or "DEFLATE" (lossless).
        """
        from geonav.outputs import check_replaceable, not_a_scene_package, output_lock

        out = Path(out_dir)
        with output_lock(out, "--out"):
            # under the lock: a second writer cannot slip in between the check and the rename
            check_replaceable(out, "scene package", force=overwrite,
                              why_not=not_a_scene_package, error=SceneError)
            manifest = self._write_package(Path(os.path.abspath(out)), compress)
        self.manifest, self.path = manifest, out
        self.__dict__.pop("_mapped", None)  # the arrays are not the new package's decoding
        log.info("wrote scene %s to %s (%dx%d px at %.3f m)", self.name, out, self.width,
                 self.height, self.gsd_m)
        return out

    def _write_package(self, out: Path, compress: str) -> dict[str, Any]:
        """Write the package into a temporary sibling of ``out`` and rename it into place."""
        import rasterio
        from rasterio._err import CPLE_BaseError
        from rasterio.errors import RasterioError

        from geonav.outputs import replace_dir

        out.parent.mkdir(parents=True, exist_ok=True)
        clean_stale_temps(out.parent, out.name)
        tmp = temp_dir(out.parent, out.name)
        tmp.chmod(0o755)
        try:
            crs = self.frame.crs.to_wkt()
            profile: dict[str, Any] = dict(
                driver="COG", width=self.width, height=self.height, transform=self.transform,
                crs=crs, blocksize=512, overview_resampling="average", BIGTIFF="IF_SAFER",
            )
            rgb_opts = dict(compress=compress, quality=92) if compress.upper() == "JPEG" else \
                dict(compress=compress, predictor=2)
            try:
                with rasterio.open(tmp / ORTHO, "w", count=3, dtype="uint8", **profile,
                                   **rgb_opts) as dst:
                    dst.write(np.moveaxis(self.rgb, 2, 0))
                    dst.write_mask(self.mask.astype(np.uint8) * 255)
                if self.dsm is not None:
                    with rasterio.open(tmp / DSM, "w", count=1, dtype="float32",
                                       nodata=float("nan"), compress="DEFLATE", predictor=3,
                                       **profile) as dst:
                        dst.write(self.dsm.astype(np.float32), 1)
            except (RasterioError, CPLE_BaseError) as err:  # a full disk, a quota
                raise SceneError(f"cannot write the scene package {out}: "
                                 f"{' '.join(str(err).split())[:300]}; free disk space or "
                                 "choose another output folder") from err
            manifest = self._manifest(tmp)
            try:
                text = json.dumps(manifest, indent=2, allow_nan=False)
            except ValueError as err:  # NaN/inf is not JSON: refuse rather than write it
                raise SceneError(f"scene {self.name!r}: the manifest holds a non-finite "
                                 f"number ({err}); check --ground-alt and --origin") from err
            (tmp / MANIFEST).write_text(text)
            replace_dir(tmp, out)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return manifest

    def _manifest(self, folder: Path) -> dict[str, Any]:
        xmin, ymin, xmax, ymax = self.bounds_m
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
            # [west, south, east, north]; west > east when the scene crosses 180 degrees
            bounds_wgs84=grid_bounds_wgs84(self.frame, self.bounds_m),
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
        """Open and validate a scene package; SceneError names each problem found.

        Besides the manifest's fields and types, the rasters must agree with it:
        ortho and DSM on the manifest grid (size, transform, CRS), ``gsd_m`` equal
        to the transform's pixel size, ``bounds_m`` and ``bounds_wgs84`` those of the
        grid, and the CRS centred on the recorded origin (else the flight frame would
        be displaced). A raster's sha256 is checked whenever it is decoded (the first
        open, and after the file changed); ``verify_checksums`` checks it on every open.
        """
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
        if verify_checksums:
            problems += checksum_problems(folder, manifest)
        try:
            origin = LonLat(**{k: float(manifest["origin"][k])
                               for k in ("lon_deg", "lat_deg", "alt_m")})
        except GeonavError as err:
            raise SceneError(f"{folder / MANIFEST}: origin is invalid: {err}") from err
        transform = Affine(*manifest["transform"])
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
                rgb, mask = mapped_ortho(ortho_path, src, manifest["ortho"].get("sha256"))
                ortho_crs = src.crs
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
                    shift = math.hypot(src.transform.c - transform.c,
                                       src.transform.f - transform.f)
                    if (not np.allclose(list(src.transform)[:6], manifest["transform"],
                                        atol=1e-6) or src.crs is None
                            or not parse_crs(src.crs.to_wkt()).equals(
                                parse_crs(ortho_crs.to_wkt()))):
                        raise SceneError(
                            f"{dsm_path.name} is not on the ortho grid: its transform is "
                            f"{list(src.transform)[:6]} ({shift:.1f} m from the ortho's "
                            f"corner) and CRS {'missing' if src.crs is None else 'given'}; "
                            "re-ingest the scene with --dsm")
                    if src.count != 1:
                        raise SceneError(f"{dsm_path.name} must have one band, has {src.count}")
                    dsm = mapped_dsm(dsm_path, src, manifest["dsm"].get("sha256"))
        except RasterioError as err:
            raise SceneError(f"cannot read the rasters of {folder}: {err}") from err
        check_origin(folder, manifest, origin)
        if not math.isclose(transform.a, -transform.e, rel_tol=1e-9) or transform.b or transform.d:
            raise SceneError(f"scene {folder}: pixels must be square and north-up, transform "
                             f"is {manifest['transform']}")
        if not math.isclose(float(manifest["gsd_m"]), transform.a, rel_tol=1e-6):
            raise SceneError(f"scene {folder}: gsd_m {manifest['gsd_m']} disagrees with the "
                             f"transform's pixel size {transform.a}; re-create the package")
        if dsm is not None and np.isinf(dsm).any():
            raise SceneError(f"scene {folder}: {manifest['dsm']['file']} holds infinite heights")
        check_bounds(folder, manifest, transform, origin)
        scene = cls(manifest["name"], rgb, mask, float(manifest["gsd_m"]), transform, origin,
                    dsm, manifest, folder)
        scene.__dict__["_mapped"] = (rgb, mask, dsm)
        return scene


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
