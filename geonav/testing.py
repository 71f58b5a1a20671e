"""Small scenes and tasks built in code, for tests, examples and benchmarks.

Nothing here reads files or downloads anything; every scene is deterministic
by seed.
"""

from __future__ import annotations

import cv2
import numpy as np

from geonav.geo import LonLat
from geonav.scene import Scene
from geonav.tasks import NavTask, ObstacleModel, TaskSet

TEST_ORIGIN = LonLat(4.4777, 51.9244, 2.0)


def textured_scene(size_m: float = 400.0, gsd_m: float = 0.5, seed: int = 0, *,
                   name: str = "T", towers: bool = True,
                   origin: LonLat = TEST_ORIGIN) -> Scene:
    """A scene of multi-scale colour noise (every place looks different) with a DSM.

    With ``towers`` the DSM holds a few 60 m towers and 12 m houses, so that
    cells are blocked at 15 m and 45 m but not at 75 m (default obstacle model).
    """
    rng = np.random.default_rng(seed)
    n = int(round(size_m / gsd_m))
    img = np.zeros((n, n, 3), np.float32)
    for cells, weight in ((4, 0.5), (16, 0.3), (64, 0.15), (256, 0.05)):
        small = rng.random((cells, cells, 3)).astype(np.float32)
        img += weight * cv2.resize(small, (n, n), interpolation=cv2.INTER_CUBIC)
    img += rng.normal(0, 0.02, img.shape).astype(np.float32)
    rgb = np.clip(img * 255, 0, 255).astype(np.uint8)
    dsm = np.zeros((n, n), np.float32)
    if towers:
        for _ in range(max(1, int(size_m / 100))):
            r, c = rng.integers(n // 8, n - n // 8, 2)
            half = int(6 / gsd_m)
            dsm[r - half:r + half, c - half:c + half] = 60.0
            rgb[r - half:r + half, c - half:c + half] = (200, 200, 205)
        for _ in range(int((size_m / 40) ** 2)):
            r, c = rng.integers(0, n - 10, 2)
            dsm[r:r + int(8 / gsd_m), c:c + int(8 / gsd_m)] = 12.0
    return Scene.from_arrays(name, rgb, origin, gsd_m, dsm=dsm)


def tiny_taskset(scene: Scene, *, alt_m: float = 75.0, cells: int = 4, step_m: float = 15.0,
                 max_steps: int = 30, target: tuple[int, int] | None = None) -> TaskSet:
    """One task on a ``cells`` x ``cells`` lattice at the scene centre."""
    half = cells * step_m / 2
    region = (-half, -half, half, half)
    task = NavTask("tiny", "meta", region, step_m, alt_m, target or (cells - 1, cells - 1),
                   max_steps, ObstacleModel())
    return TaskSet(scene.name, scene.scene_id, [task])
