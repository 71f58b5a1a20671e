"""Decoded scene rasters as read-only memory maps, shared by every process that opens them.

:meth:`geonav.scene.Scene.open` decodes a package's ortho and DSM once into ``.npy``
files (:func:`mapped_ortho`, :func:`mapped_dsm`) in the package's raster cache
(:func:`raster_cache_dir`), keyed by the file's identity (:func:`file_key`); later
opens, in any process, only map them (:func:`cached_array`), so vector-env workers
share one copy in the page cache.
"""

from __future__ import annotations

import hashlib
import logging
import os
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from geonav.scene_package import verify_sha256

log = logging.getLogger(__name__)

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


def mapped_ortho(path: Path, src: Any, sha256: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The ortho's (H, W, 3) uint8 pixels and (H, W) bool mask as read-only memory maps.

    Decoded from the open dataset ``src`` on first use into the package's raster cache
    (:func:`raster_cache_dir`); later opens, in any process, only map the files. A
    decode first checks the file against ``sha256`` (its manifest's), when given.
    """
    cache, key = raster_cache_dir(path.parent), file_key(path)

    def decode() -> np.ndarray:
        verify_sha256(path, sha256)
        return np.moveaxis(src.read(), 0, 2)

    rgb = cached_array(cache / f"{path.stem}.rgb-{key}.npy", decode)
    mask = cached_array(cache / f"{path.stem}.mask-{key}.npy", lambda: src.dataset_mask() > 0)
    return rgb, mask


def mapped_dsm(path: Path, src: Any, sha256: str | None = None) -> np.ndarray:
    """The DSM's (H, W) float32 metres as a read-only memory map (see :func:`mapped_ortho`)."""
    cache, key = raster_cache_dir(path.parent), file_key(path)

    def decode() -> np.ndarray:
        verify_sha256(path, sha256)
        return src.read(1).astype(np.float32)

    return cached_array(cache / f"{path.stem}.dsm-{key}.npy", decode)
