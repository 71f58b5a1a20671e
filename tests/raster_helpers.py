"""Small GeoTIFFs for the malformed-input tests: a texture, a writer and a UTM fixture
(shared by tests/test_malformed_inputs.py and tests/test_malformed_inputs2.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from affine import Affine

UTM31 = "EPSG:32631"
X0, Y0 = 594000.0, 5754000.0  # Rotterdam in UTM 31N


def write_raster(path: Path, data: np.ndarray, crs: str, transform: Affine, **kw) -> Path:
    """Write (bands, h, w) or (h, w) ``data`` as a GeoTIFF."""
    import rasterio

    data = data if data.ndim == 3 else data[None]
    with rasterio.open(path, "w", driver="GTiff", width=data.shape[2], height=data.shape[1],
                       count=data.shape[0], dtype=data.dtype, crs=crs, transform=transform,
                       **kw) as dst:
        dst.write(data)
    return path


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """(3, h, w) uint8 random texture (enough structure for the resamplers)."""
    rng = np.random.default_rng(seed)
    return (60 + rng.integers(0, 80, (3, h, w))).astype(np.uint8)


def make_utm_tif(tmp_path_factory) -> Path:
    """160 x 160 m of texture at 1 m in UTM 31N (the modules' ``utm_tif`` fixture)."""
    d = tmp_path_factory.mktemp("utm")
    return write_raster(d / "utm.tif", texture(160, 160), UTM31, Affine(1, 0, X0, 0, -1, Y0))
