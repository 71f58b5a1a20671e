"""Nadir pinhole camera over a scene, with two render paths and one camera model.

The camera looks straight down; its square image of ``size_px`` pixels spans a
horizontal field of view ``fov_deg``, so the ground footprint side is
``2 * alt_m * tan(fov/2)`` (600 m at 300 m, 30 m at 15 m with 90 degrees) and
each image pixel covers ``footprint / size_px`` metres. Image "up" is the
heading (north unless a yaw is given); pixel (u, v) has u to the right and v
down, and its centre sees the ground point
``centre + res * (du * right - dv * up)`` with ``du = u - (N-1)/2``,
``dv = v - (N-1)/2``.

* :class:`SliceRenderer` (training): north-up, discrete altitudes. One map per
  altitude, area-averaged once to that altitude's image resolution; each view
  is then an array slice (positions snap to the map's pixel, at most half an
  image pixel away).
* :class:`WarpRenderer` (anywhere else): an area-averaged pyramid, the level
  just finer than the image resolution, one bilinear ``cv2.warpAffine`` for any
  float position and yaw.

Outside the imagery (or its mask) the image is filled with ``fill`` and the
valid fraction is reported by :meth:`coverage`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from geonav.errors import CameraError
from geonav.scene import Scene, cached_array, file_key, raster_cache_dir

cv2.setNumThreads(1)  # parallelism comes from env workers, not from OpenCV threads


@dataclass(frozen=True)
class Camera:
    """A square nadir pinhole camera.

    Attributes:
        size_px: image side in pixels (N).
        fov_deg: horizontal (= vertical) field of view in degrees.
    """

    size_px: int = 84
    fov_deg: float = 90.0

    def __post_init__(self) -> None:
        if not 8 <= self.size_px <= 1024:
            raise CameraError(f"size_px must be within 8..1024, got {self.size_px}")
        if not 1.0 <= self.fov_deg < 170.0:
            raise CameraError(f"fov_deg must be within 1..170 degrees, got {self.fov_deg}")

    def footprint_m(self, alt_m: float) -> float:
        """Side of the ground square seen from ``alt_m`` metres above ground."""
        if alt_m <= 0:
            raise CameraError(f"altitude must be positive, got {alt_m} m")
        return 2.0 * alt_m * math.tan(math.radians(self.fov_deg) / 2.0)

    def ground_res_m(self, alt_m: float) -> float:
        """Metres of ground per image pixel at ``alt_m``."""
        return self.footprint_m(alt_m) / self.size_px

    def focal_px(self) -> float:
        return (self.size_px / 2.0) / math.tan(math.radians(self.fov_deg) / 2.0)


@dataclass
class _AltitudeMap:
    rgb: np.ndarray  # (pad + Hm + pad, pad + Wm + pad, 3) uint8, read-only
    valid: np.ndarray | None  # same H, W; float32 fraction of valid source pixels (lazy)
    res_x_m: float  # map pixel size east
    res_y_m: float  # map pixel size north
    pad: int


class SliceRenderer:
    """North-up views at discrete altitudes by slicing prefiltered maps.

    The maps are shared: every renderer of the same scene object, camera and fill (so
    every env of one process over one scene) uses one map per altitude, stored on the
    scene. For a scene opened from a package the map is also written once into the
    package's raster cache and memory-mapped, so processes share its pages (one
    vector-env worker costs little more than its interpreter).

    Args:
        scene: the scene.
        camera: the camera.
        fill: value for pixels outside the imagery.
    """

    def __init__(self, scene: Scene, camera: Camera | None = None, fill: int = 0) -> None:
        self.scene = scene
        self.camera = camera or Camera()
        self.fill = int(fill)
        # shared per scene object; a scene whose rgb or mask was replaced starts afresh
        shared: dict[tuple[Camera, int], tuple[np.ndarray, np.ndarray,
                                                dict[float, _AltitudeMap]]] = \
            scene.__dict__.setdefault("_slice_maps", {})
        key = (self.camera, self.fill)
        entry = shared.get(key)
        if entry is None or entry[0] is not scene.rgb or entry[1] is not scene.mask:
            entry = shared[key] = (scene.rgb, scene.mask, {})
        self._maps: dict[float, _AltitudeMap] = entry[2]

    def _map(self, alt_m: float) -> _AltitudeMap:
        key = float(alt_m)
        if key not in self._maps:
            self._maps[key] = self._build(key)
        return self._maps[key]

    def _grid(self, alt_m: float) -> tuple[float, int, int]:
        """(image resolution in m/px, map width px, map height px) at ``alt_m``."""
        res_m = self.camera.ground_res_m(alt_m)
        width_m, height_m = self.scene.size_m
        return res_m, max(1, round(width_m / res_m)), max(1, round(height_m / res_m))

    def _resized_valid(self, alt_m: float) -> np.ndarray:
        res_m, mw, mh = self._grid(alt_m)
        interp = cv2.INTER_AREA if res_m >= self.scene.gsd_m else cv2.INTER_NEAREST
        return cv2.resize(self.scene.mask.astype(np.float32), (mw, mh), interpolation=interp)

    def _build(self, alt_m: float) -> _AltitudeMap:
        scene, n = self.scene, self.camera.size_px
        res_m, mw, mh = self._grid(alt_m)
        pad = n + 2

        def build_rgb() -> np.ndarray:
            # area averaging down to the view's resolution; imagery coarser than the view
            # is upsampled (warned about at ingestion)
            interp = cv2.INTER_AREA if res_m >= scene.gsd_m else cv2.INTER_LINEAR
            rgb = cv2.resize(scene.rgb, (mw, mh), interpolation=interp)
            if not scene.mask.all():
                rgb[self._resized_valid(alt_m) < 0.5] = self.fill
            return cv2.copyMakeBorder(rgb, pad, pad, pad, pad, cv2.BORDER_CONSTANT,
                                      value=(self.fill,) * 3)

        path = self._cache_path(alt_m)
        if path is not None:
            rgb = cached_array(path, build_rgb)
        else:
            rgb = np.ascontiguousarray(build_rgb())
            rgb.flags.writeable = False
        width_m, height_m = scene.size_m
        return _AltitudeMap(rgb, None, width_m / mw, height_m / mh, pad)

    def _cache_path(self, alt_m: float) -> Path | None:
        """Where the map of a package scene is cached; None for in-memory or edited scenes."""
        scene = self.scene
        if not scene.is_mapped() or scene.path is None:
            return None
        ortho = scene.path / scene.manifest.get("ortho", {}).get("file", "ortho.tif")
        try:
            key, folder = file_key(ortho), raster_cache_dir(scene.path)
        except OSError:
            return None
        cam = self.camera
        return folder / (f"slice-{cam.size_px}px-{cam.fov_deg:g}deg-{alt_m:g}m-fill{self.fill}"
                         f".rgb-{key}.npy")

    def _valid(self, alt_m: float) -> np.ndarray:
        m = self._map(alt_m)
        if m.valid is None:
            pad = m.pad
            m.valid = cv2.copyMakeBorder(self._resized_valid(alt_m), pad, pad, pad, pad,
                                         cv2.BORDER_CONSTANT, value=0.0)
        return m.valid

    def _origin_px(self, m: _AltitudeMap, x_m: float, y_m: float) -> tuple[int, int]:
        n = self.camera.size_px
        xmin, _, _, ymax = self.scene.bounds_m
        col = round((x_m - xmin) / m.res_x_m - n / 2) + m.pad
        row = round((ymax - y_m) / m.res_y_m - n / 2) + m.pad
        if not (0 <= col <= m.rgb.shape[1] - n and 0 <= row <= m.rgb.shape[0] - n):
            raise CameraError(f"the view at ({x_m:.1f}, {y_m:.1f}) m lies outside scene "
                              f"{self.scene.name!r} (bounds {self.scene.bounds_m})")
        return row, col

    def snap(self, x_m: float, y_m: float, alt_m: float) -> tuple[float, float]:
        """The centre (x_m, y_m) of the view that :meth:`render` returns for this request."""
        m = self._map(alt_m)
        row, col = self._origin_px(m, x_m, y_m)
        n = self.camera.size_px
        xmin, _, _, ymax = self.scene.bounds_m
        return (xmin + (col - m.pad + n / 2) * m.res_x_m,
                ymax - (row - m.pad + n / 2) * m.res_y_m)

    def render(self, x_m: float, y_m: float, alt_m: float) -> np.ndarray:
        """The (N, N, 3) uint8 view centred at scene (x_m, y_m) from ``alt_m`` (a new array)."""
        return self.view(x_m, y_m, alt_m).copy()

    def view(self, x_m: float, y_m: float, alt_m: float) -> np.ndarray:
        """The same view as :meth:`render`, as a read-only slice of the shared map (no copy)."""
        m = self._map(alt_m)
        row, col = self._origin_px(m, x_m, y_m)
        n = self.camera.size_px
        return m.rgb[row:row + n, col:col + n]

    def coverage(self, x_m: float, y_m: float, alt_m: float) -> float:
        """Fraction of the view that sees valid imagery (1.0 = fully inside)."""
        m = self._map(alt_m)
        row, col = self._origin_px(m, x_m, y_m)
        n = self.camera.size_px
        return float(self._valid(alt_m)[row:row + n, col:col + n].mean())


class WarpRenderer:
    """Views at any float position, altitude and yaw: area pyramid + one warpAffine.

    Args:
        scene: the scene.
        camera: the camera.
        fill: value for pixels outside the imagery.
    """

    def __init__(self, scene: Scene, camera: Camera | None = None, fill: int = 0) -> None:
        self.scene = scene
        self.camera = camera or Camera()
        self.fill = int(fill)
        rgb = scene.rgb
        if not scene.mask.all():
            rgb = rgb.copy()
            rgb[~scene.mask] = self.fill
        self._levels: list[np.ndarray] = [rgb]
        self._valid: list[np.ndarray] = [scene.mask.astype(np.float32)]

    def _level(self, level: int) -> np.ndarray:
        while len(self._levels) <= level:
            prev = self._levels[-1]
            size = (max(1, prev.shape[1] // 2), max(1, prev.shape[0] // 2))
            self._levels.append(cv2.resize(prev, size, interpolation=cv2.INTER_AREA))
            self._valid.append(cv2.resize(self._valid[-1], size, interpolation=cv2.INTER_AREA))
        return self._levels[level]

    def _matrix(self, x_m: float, y_m: float, alt_m: float, yaw_deg: float,
                size_px: int) -> tuple[int, np.ndarray]:
        scene = self.scene
        res_m = self.camera.ground_res_m(alt_m) * self.camera.size_px / size_px
        level = max(0, int(math.floor(math.log2(res_m / scene.gsd_m + 1e-9))))
        level = min(level, max(0, int(math.log2(min(scene.width, scene.height))) - 2))
        img = self._level(level)
        res_x, res_y = scene.size_m[0] / img.shape[1], scene.size_m[1] / img.shape[0]
        xmin, _, _, ymax = scene.bounds_m
        cos, sin = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
        c0 = (size_px - 1) / 2.0
        a, b = res_m * cos / res_x, -res_m * sin / res_x
        d, e = res_m * sin / res_y, res_m * cos / res_y
        m = np.array([
            [a, b, (x_m - xmin) / res_x - 0.5 - (a + b) * c0],
            [d, e, (ymax - y_m) / res_y - 0.5 - (d + e) * c0],
        ])
        return level, m

    def render(self, x_m: float, y_m: float, alt_m: float, yaw_deg: float = 0.0) -> np.ndarray:
        """The (N, N, 3) uint8 view at scene (x_m, y_m), ``alt_m`` above ground, heading yaw.

        Args:
            x_m: east in the scene CRS.
            y_m: north in the scene CRS.
            alt_m: altitude above ground, metres.
            yaw_deg: heading, clockwise from north (NED yaw); image up = heading.
        """
        n = self.camera.size_px
        level, m = self._matrix(x_m, y_m, alt_m, yaw_deg, n)
        return cv2.warpAffine(self._levels[level], m, (n, n),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=(self.fill,) * 3)

    def coverage(self, x_m: float, y_m: float, alt_m: float, yaw_deg: float = 0.0) -> float:
        """Fraction of the view that sees valid imagery, estimated on a 16x16 grid."""
        level, m = self._matrix(x_m, y_m, alt_m, yaw_deg, 16)
        self._level(level)
        valid = cv2.warpAffine(self._valid[level], m, (16, 16),
                               flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        return float(valid.mean())


def render(scene: Scene, x_m: float, y_m: float, alt_m: float, yaw_deg: float = 0.0,
           camera: Camera | None = None) -> np.ndarray:
    """One view from anywhere (warp path); the renderer is cached on the scene object."""
    camera = camera or Camera()
    cache: dict[Camera, WarpRenderer] = scene.__dict__.setdefault("_warp_renderers", {})
    if camera not in cache:
        cache[camera] = WarpRenderer(scene, camera)
    return cache[camera].render(x_m, y_m, alt_m, yaw_deg)
