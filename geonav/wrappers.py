"""Observation wrappers for GeoNavEnv's Dict space.

Gymnasium's ``ResizeObservation`` and ``GrayscaleObservation`` accept a Box only,
so they refuse ``Dict(image=..., target=...)``. :class:`DictImageObservation`
applies the same two transforms (area-averaged resize, ITU-R 601 grey) to each
image key of a Dict space and leaves the other keys alone.

To get views of another size at the source instead, pass a camera:
``GeoNavEnv(scene, tasks, camera=Camera(size_px=64))`` renders 64 px views from the
imagery itself (sharper than resizing 84 px views; the task margins are checked
for that camera). The wrapper is for what a camera cannot do: grey, non-square
sizes, or resizing an env you did not build.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from geonav.errors import ConfigError


def _is_rgb_image(space: gym.Space[Any]) -> bool:
    return (isinstance(space, spaces.Box) and space.dtype == np.uint8
            and len(space.shape) == 3 and space.shape[2] == 3)


class DictImageObservation(gym.ObservationWrapper[dict[str, np.ndarray], Any, Any],
                           gym.utils.RecordConstructorArgs):
    """Resize and/or grey each (H, W, 3) uint8 image key of a Dict observation.

    Args:
        env: an env with a ``Dict`` observation space (GeoNavEnv or a wrapper of it).
        shape: output (height, width) in pixels, or one int for a square; None keeps
            the size. Downsampling averages areas (``cv2.INTER_AREA``, as Gymnasium's
            ``ResizeObservation``); upsampling is bilinear.
        grey: convert to luminance (``cv2.COLOR_RGB2GRAY``: 0.299 R + 0.587 G + 0.114 B).
        keep_dim: with ``grey``, keep a channel axis, (H, W, 1), so that image-aware
            learners (SB3's ``CnnPolicy``/``MultiInputPolicy``) still see an image;
            False gives (H, W) as Gymnasium's ``GrayscaleObservation`` does by default.
        keys: the keys to transform (default: every (H, W, 3) uint8 Box key).

    Raises:
        ConfigError: the space is not a Dict, a key is missing or not an RGB image,
            or the shape is not positive.
    """

    def __init__(self, env: gym.Env[Any, Any], shape: int | tuple[int, int] | None = None,
                 *, grey: bool = False, keep_dim: bool = True,
                 keys: Sequence[str] | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, shape=shape, grey=grey,
                                                 keep_dim=keep_dim, keys=keys)
        gym.ObservationWrapper.__init__(self, env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict):
            raise ConfigError(f"DictImageObservation needs a Dict observation space, got {space}")
        if isinstance(shape, int):
            shape = (shape, shape)
        if shape is not None and (len(shape) != 2 or min(shape) < 1):
            raise ConfigError(f"shape must be (height, width) in pixels, got {shape}")
        if keys is None:
            keys = [k for k, s in space.spaces.items() if _is_rgb_image(s)]
        for key in keys:
            if key not in space.spaces or not _is_rgb_image(space.spaces[key]):
                raise ConfigError(f"key {key!r} is not an (H, W, 3) uint8 image of {space}")
        self.shape = None if shape is None else (int(shape[0]), int(shape[1]))
        self.grey, self.keep_dim = bool(grey), bool(keep_dim)
        self.keys = tuple(keys)
        out = dict(space.spaces)
        for key in self.keys:
            h, w = self.shape or tuple(space.spaces[key].shape or (0, 0))[:2]
            dims: tuple[int, ...] = (h, w, 3) if not self.grey else \
                ((h, w, 1) if self.keep_dim else (h, w))
            out[key] = spaces.Box(0, 255, dims, np.uint8)
        self.observation_space = spaces.Dict(out)  # type: ignore[assignment]

    def _image(self, img: np.ndarray) -> np.ndarray:
        if self.shape is not None and img.shape[:2] != self.shape:
            h, w = self.shape
            interp = cv2.INTER_AREA if h * w < img.shape[0] * img.shape[1] else cv2.INTER_LINEAR
            img = cv2.resize(img, (w, h), interpolation=interp)
        if self.grey:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
            if self.keep_dim:
                img = img[:, :, None]
        return np.ascontiguousarray(img)

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        out = dict(observation)
        for key in self.keys:
            out[key] = self._image(observation[key])
        return out


class ImageryRandomisation(gym.Wrapper[dict[str, np.ndarray], Any, dict[str, np.ndarray], Any],
                           gym.utils.RecordConstructorArgs):
    """Seeded imagery randomisation of GeoNavEnv's views (see :mod:`geonav.augment`).

    One variant is drawn per episode at ``reset`` and applied to both the current view
    and the target view for the whole episode (the reason is in
    :class:`geonav.vecenv.LatticeVecEnv`'s docstring); ``reset(options={"variant": k})``
    forces variant k, and ``info["augment_variant"]`` says which one is in use. The
    pixels of variant k are exactly those of row ``k * n_cells + view`` of the batched
    engine's table (``LatticeVecEnv`` on this wrapper builds its tables from the same
    :class:`~geonav.augment.AugmentConfig`), so the two agree.

    The per-episode draw comes from the wrapper's own generator, seeded from
    ``reset(seed=s)`` (an unseeded first reset seeds it from the OS), so the wrapped
    env's own draws (task, start) are those of the bare env.

    Args:
        env: a GeoNavEnv or a wrapper of it with its ``Dict(image, target)`` space.
        config: an :class:`~geonav.augment.AugmentConfig` or a mapping of its fields.
    """

    def __init__(self, env: gym.Env[Any, Any], config: Any = None) -> None:
        from geonav.augment import AugmentConfig

        cfg = AugmentConfig.from_dict({} if config is None else config)
        gym.utils.RecordConstructorArgs.__init__(self, config=cfg.to_dict())
        gym.Wrapper.__init__(self, env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or not all(
                k in space.spaces and _is_rgb_image(space.spaces[k]) for k in ("image", "target")):
            raise ConfigError(f"ImageryRandomisation needs GeoNavEnv's Dict(image, target) "
                              f"space of (N, N, 3) uint8 images, got {space}")
        self.augment = cfg
        self._params = [cfg.params(k) for k in range(cfg.n_variants)]
        self._rng: np.random.Generator | None = None
        self.variant = 0
        self._target: np.ndarray | None = None
        self._target_key: Any = None

    def _apply(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        from geonav.augment import augment_image

        p = self._params[self.variant]
        key = (self.variant, info.get("task_index"), info.get("target_cell"))
        if self._target is None or key != self._target_key:
            self._target, self._target_key = augment_image(obs["target"], p), key
        out = dict(obs)
        out["image"] = augment_image(obs["image"], p)
        out["target"] = self._target.copy()
        info["augment_variant"] = self.variant
        return out

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None
              ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        options = dict(options or {})
        forced = options.pop("variant", None)
        if seed is not None or self._rng is None:
            self._rng = np.random.default_rng(
                None if seed is None else np.random.SeedSequence([0x61756776, int(seed)]))
        if forced is not None:
            if not 0 <= int(forced) < self.augment.n_variants:
                raise ConfigError(f"variant {forced} out of range "
                                  f"0..{self.augment.n_variants - 1}")
            self.variant = int(forced)
        else:
            self.variant = int(self._rng.integers(self.augment.n_variants))
        obs, info = self.env.reset(seed=seed, options=options or None)
        return self._apply(obs, info), info

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], Any, bool, bool,
                                         dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        return self._apply(obs, info), reward, terminated, truncated, info
