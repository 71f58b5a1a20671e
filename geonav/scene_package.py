"""The scene package on disk: its file names, ``scene.json`` checks, checksums, temp folders.

A scene package (DESIGN.md "Scene package") is a folder of ``ortho.tif``, an optional
``dsm.tif`` and ``scene.json``. This module reads and checks the manifest
(:func:`read_manifest`: every missing or mistyped field named; :func:`check_bounds`
and :func:`check_origin`: the recorded bounds and origin agree with the grid and CRS),
the rasters' sha256 (:func:`sha256_file`, :func:`verify_sha256`), and the temporary
folders a package is written into before it is renamed into place (:func:`temp_dir`,
:func:`clean_stale_temps`). :class:`geonav.scene.Scene` loads and saves packages with
it; its names are re-exported from :mod:`geonav.scene`.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from affine import Affine

from geonav.errors import GeonavWarning, SceneError
from geonav.geo import LonLat, SceneFrame, ScenePoint, parse_crs, transformer

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


_TMP_TAG = "geonav-tmp"


def temp_dir(parent: Path, stem: str) -> Path:
    """A new hidden temporary folder ``parent/.{stem}.geonav-tmp-{pid}-XXXX``.

    The pid in the name lets a later run tell a folder of a killed run (its process
    is gone) from one still being written (:func:`clean_stale_temps`).
    """
    parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{stem}.{_TMP_TAG}-{os.getpid()}-", dir=parent))


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OSError):
        return True  # someone else's process, or cannot tell: leave its folder alone
    return True


def clean_stale_temps(parent: Path, stem: str) -> list[Path]:
    """Remove the temporary folders of ``stem`` whose writing process no longer runs.

    A run killed with SIGKILL (or a power cut) cannot clean up after itself; the
    next run does, and says so with a warning. Returns the folders removed.
    """
    import warnings

    removed = []
    if not parent.is_dir():
        return removed
    for entry in parent.glob(f".{stem}.{_TMP_TAG}-*"):
        try:
            pid = int(entry.name[len(f".{stem}.{_TMP_TAG}-"):].split("-", 1)[0])
        except ValueError:
            continue
        if entry.is_dir() and pid != os.getpid() and not _pid_alive(pid):
            shutil.rmtree(entry, ignore_errors=True)
            removed.append(entry)
            warnings.warn(f"removed {entry}, a temporary folder left by a killed run "
                          f"(pid {pid})", GeonavWarning, stacklevel=3)
    return removed


def lon_span(lons: list[float]) -> tuple[float, float]:
    """(west, east) of corner longitudes; west > east when they straddle 180 degrees."""
    if max(lons) - min(lons) > 180.0:  # the short way round crosses the antimeridian
        return min(x for x in lons if x > 0), max(x for x in lons if x < 0)
    return min(lons), max(lons)


def checksum_problems(folder: Path, manifest: dict[str, Any]) -> list[str]:
    """The package's rasters whose bytes no longer match their sha256 in the manifest."""
    problems = []
    for key in ("ortho", "dsm"):
        entry = manifest.get(key)
        if isinstance(entry, dict) and (folder / entry["file"]).is_file() and \
                sha256_file(folder / entry["file"]) != entry.get("sha256"):
            problems.append(f"{entry['file']} does not match its sha256 in {MANIFEST} (the "
                            "file changed after geonav wrote it); re-create the package")
    return problems


def verify_sha256(path: Path, expected: str | None) -> None:
    """SceneError when the file's sha256 is not the one its manifest records."""
    if expected is not None and sha256_file(path) != expected:
        raise SceneError(f"{path} does not match its sha256 in {MANIFEST} (the file changed "
                         "after geonav wrote it); re-create the package with 'geonav tiles "
                         "ingest ... --force'")


#: How far a recorded bound may sit from the grid's own: 1 mm, and 1e-7 degrees (1 cm).
BOUNDS_TOL_M, BOUNDS_TOL_DEG = 1e-3, 1e-7


def grid_bounds_wgs84(frame: SceneFrame, bounds_m: tuple[float, ...]) -> list[float]:
    """[west, south, east, north] of a scene-metre box; west > east across 180 degrees."""
    xmin, ymin, xmax, ymax = bounds_m
    corners = [frame.to_lonlat(ScenePoint(x, y)) for x in (xmin, xmax) for y in (ymin, ymax)]
    west, east = lon_span([c.lon_deg for c in corners])
    return [west, min(c.lat_deg for c in corners), east, max(c.lat_deg for c in corners)]


def check_bounds(folder: Path, manifest: dict[str, Any], transform: Affine,
                  origin: LonLat) -> None:
    # The bounds are what readers of scene.json (and task sampling by hand) go by: a
    # hand-edited pair that no longer describes the grid would mislead them silently.
    w, h, gsd = manifest["width"], manifest["height"], transform.a
    grid = (transform.c, transform.f - h * gsd, transform.c + w * gsd, transform.f)
    if not np.allclose(manifest["bounds_m"], grid, rtol=0, atol=BOUNDS_TOL_M):
        raise SceneError(f"scene {folder}: bounds_m {manifest['bounds_m']} is not the grid's "
                         f"{[round(v, 3) for v in grid]} (transform and size); scene.json was "
                         "edited by hand: re-create the package")
    wgs84 = grid_bounds_wgs84(SceneFrame(origin), grid)
    if not np.allclose(manifest["bounds_wgs84"], wgs84, rtol=0, atol=BOUNDS_TOL_DEG):
        raise SceneError(f"scene {folder}: bounds_wgs84 {manifest['bounds_wgs84']} is not the "
                         f"grid's {[round(v, 7) for v in wgs84]}; scene.json was edited by "
                         "hand: re-create the package")


#: How far (m) the recorded origin may sit from the centre of the recorded CRS.
ORIGIN_TOL_M = 0.01


def check_origin(folder: Path, manifest: dict[str, Any], origin: LonLat) -> None:
    # The flight frame is built from the origin, the pixels from the CRS: they must agree.
    crs = parse_crs(manifest["crs_wkt2"])
    try:
        x, y = transformer(parse_crs("EPSG:4326"), crs).transform(origin.lon_deg,
                                                                   origin.lat_deg)
    except Exception as err:  # noqa: BLE001 - any projection failure is the same problem
        raise SceneError(f"scene {folder}: the origin cannot be projected into its CRS "
                         f"({err})") from err
    off = math.hypot(x, y) if math.isfinite(x) and math.isfinite(y) else math.inf
    if off > ORIGIN_TOL_M:
        raise SceneError(
            f"scene {folder}: origin {origin.lon_deg:.7f},{origin.lat_deg:.7f} is {off:.2f} m "
            f"from the centre of crs_wkt2 (the local tmerc must be centred on the origin, "
            "or the flight frame moves); re-create the package")


_NUMBER = (int, float)
_REQUIRED: dict[str, type | tuple[type, ...]] = {
    "schema_version": int, "name": str, "crs_wkt2": str, "gsd_m": _NUMBER,
    "transform": list, "width": int, "height": int, "bounds_m": list, "bounds_wgs84": list,
    "origin": dict, "ortho": dict, "sources": list,
}


def _non_finite(value: Any, where: str) -> list[str]:
    """Key paths of NaN/inf numbers anywhere in a parsed JSON value."""
    if isinstance(value, float) and not math.isfinite(value):
        return [where]
    if isinstance(value, dict):
        return [p for k, v in value.items() for p in _non_finite(v, f"{where}.{k}")]
    if isinstance(value, list):
        return [p for i, v in enumerate(value) for p in _non_finite(v, f"{where}[{i}]")]
    return []


def _is_number(v: Any) -> bool:
    return isinstance(v, _NUMBER) and not isinstance(v, bool)


def _plain_file(v: Any) -> bool:
    return isinstance(v, str) and bool(v) and "/" not in v and "\\" not in v and v not in (
        ".", "..")


def read_manifest(folder: Path) -> dict[str, Any]:
    """Read and check ``scene.json``; SceneError lists every missing or mistyped field."""
    path = folder / MANIFEST
    if not path.is_file():
        raise SceneError(f"{folder} has no {MANIFEST}; is it a scene package?")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise SceneError(f"{path} is not valid JSON ({err}); re-create the package") from err
    except OSError as err:
        raise SceneError(f"{path} cannot be read: {err.strerror or err}") from err
    if not isinstance(manifest, dict):
        raise SceneError(f"{path} must hold a JSON object")
    problems = [f"{p.removeprefix('.')!r} is not a finite number"
                for p in _non_finite(manifest, "")]
    for key, typ in _REQUIRED.items():
        if key not in manifest:
            problems.append(f"missing {key!r}")
        elif not isinstance(manifest[key], typ) or isinstance(manifest[key], bool):
            problems.append(f"{key!r} has the wrong type ({type(manifest[key]).__name__})")
    if not problems:
        if manifest["schema_version"] != SCHEMA_VERSION:
            problems.append(f"schema_version {manifest['schema_version']} is not "
                            f"{SCHEMA_VERSION}; re-ingest with this geonav")
        if not _plain_file(manifest["name"]):
            problems.append(f"'name' {manifest['name']!r} must be a non-empty name without '/'")
        for key, n in (("transform", 6), ("bounds_m", 4), ("bounds_wgs84", 4)):
            if len(manifest[key]) != n or not all(map(_is_number, manifest[key])):
                problems.append(f"{key!r} must have {n} coefficients" if key == "transform"
                                else f"{key!r} must be a list of {n} numbers")
        if manifest["gsd_m"] <= 0:
            problems.append(f"'gsd_m' must be positive, is {manifest['gsd_m']}")
        if manifest["width"] <= 0 or manifest["height"] <= 0:
            problems.append("'width' and 'height' must be positive")
        for key in ("lon_deg", "lat_deg", "alt_m"):
            if not _is_number(manifest["origin"].get(key)):
                problems.append(f"'origin.{key}' is missing or not a number")
        if not _plain_file(manifest["ortho"].get("file")):
            problems.append("'ortho.file' must be the name of a file in the package")
        dsm = manifest.get("dsm")
        if dsm is not None and not (isinstance(dsm, dict) and _plain_file(dsm.get("file"))):
            problems.append("'dsm' must be null or an object whose 'file' names a file in "
                            "the package")
        try:
            parse_crs(manifest["crs_wkt2"])
        except Exception as err:  # noqa: BLE001 - reported as a problem below
            problems.append(f"'crs_wkt2' is not a valid CRS ({err})")
    if problems:
        raise SceneError(f"{path} is invalid: " + "; ".join(problems))
    return manifest
