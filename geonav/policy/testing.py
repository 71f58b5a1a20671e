"""Tiny environments and networks for policy tests and benchmarks (no files, seconds to train)."""

from __future__ import annotations

import functools
from typing import Any

from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.policy.config import NetConfig
from geonav.testing import textured_scene, tiny_taskset


@functools.lru_cache(maxsize=4)
def _scene(seed: int) -> Any:
    return textured_scene(size_m=300.0, gsd_m=0.5, seed=seed)


def tiny_env_factory(*, cells: int = 4, max_steps: int = 10, obs_size_px: int = 32,
                     seed: int = 0, alt_m: float = 75.0) -> functools.partial[GeoNavEnv]:
    """A picklable factory of a ``cells`` x ``cells`` single-task env at one altitude."""
    scene = _scene(seed)
    ts = tiny_taskset(scene, alt_m=alt_m, cells=cells, max_steps=max_steps)
    return functools.partial(GeoNavEnv, scene, ts, camera=Camera(obs_size_px, 90.0))


def tiny_net(encoder: str = "random", obs_size_px: int = 32, size: int = 64) -> NetConfig:
    """A small network for tests."""
    return NetConfig(encoder=encoder, obs_size_px=obs_size_px, hidden_size=size, lstm_size=size)
