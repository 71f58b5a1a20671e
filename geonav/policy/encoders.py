"""Image encoders: a small trainable CNN, a frozen random CNN and a frozen ResNet18.

Trainable encoders live inside the actor-critic (their parameters are learned);
frozen ones live outside it, in a :class:`FrozenEncoder` with a feature cache
keyed by (task, cell, altitude), so each view is encoded once per process.

Images enter as uint8 ``(B, N, N, 3)`` arrays/tensors (the env's layout) and
leave as float features ``(B, F)``.
"""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from geonav.errors import CheckpointError, ConfigError, MissingExtra
from geonav.policy.config import NetConfig

log = logging.getLogger(__name__)

CacheKey = tuple[int, tuple[int, int], float] | tuple[int, tuple[int, int], float, int]
"""(task index, cell, altitude), plus the imagery variant when the env is randomised."""

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)


INPUT_NORMS = ("center", "none")


def images_to_float(images: torch.Tensor, input_norm: str = "none",
                    dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """uint8 (B, N, N, 3) -> float (B, 3, N, N), float32 unless ``dtype`` says otherwise
    (the trainable CNN passes its weights' dtype, so a float64 network takes uint8 views).

    ``input_norm='none'``: [0, 1]. ``'center'``: (x/255 - 0.5) / 0.25, so about [-2, 2]
    and zero-mean for mid-grey imagery. Why centre: with [0, 1] inputs every view shares a
    large positive component (the mean brightness), the first layers' outputs are
    dominated by it, and the cell-dependent part that navigation needs starts as a small
    perturbation (issue 10's measurements: 0.09 % of the logits' magnitude after training).
    """
    x = images.permute(0, 3, 1, 2).to(dtype)
    if input_norm == "center":
        return x.mul_(4.0 / 255.0).sub_(2.0)
    if input_norm == "none":
        return x.div_(255.0)
    raise ConfigError(f"input_norm must be one of {INPUT_NORMS}, not {input_norm!r}")


class SmallCNN(nn.Module):
    """Two strided convolutions (Mnih et al. 2013 sizes): (B, N, N, 3) uint8 -> (B, F).

    At 84 px: 8x8/4 -> 16x20x20, 4x4/2 -> 32x9x9, F = 2592.
    """

    def __init__(self, obs_size_px: int, input_norm: str = "center") -> None:
        super().__init__()
        self.input_norm = input_norm
        self.conv1 = nn.Conv2d(3, 16, kernel_size=8, stride=4)
        self.conv2 = nn.Conv2d(16, 32, kernel_size=4, stride=2)
        s1 = (obs_size_px - 8) // 4 + 1
        s2 = (s1 - 4) // 2 + 1
        if s2 < 1:
            raise ConfigError(f"obs_size_px {obs_size_px} is too small for the CNN (>= 16)")
        self.out_dim = 32 * s2 * s2

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images_to_float(images, self.input_norm, self.conv1.weight.dtype) \
            if images.dtype == torch.uint8 else images
        x = torch.relu(self.conv1(x))
        x = torch.relu(self.conv2(x))
        return x.flatten(1)


def random_cnn(obs_size_px: int, seed: int, input_norm: str = "center") -> SmallCNN:
    """A frozen :class:`SmallCNN` with weights drawn from ``seed`` (reproducible anywhere)."""
    net = SmallCNN(obs_size_px, input_norm)
    g = torch.Generator().manual_seed(int(seed))
    with torch.no_grad():
        for p in net.parameters():
            fan_in = p[0].numel() if p.dim() > 1 else 1
            if p.dim() > 1:
                p.copy_(torch.randn(p.shape, generator=g) * (2.0 / fan_in) ** 0.5)
            else:
                p.zero_()
    return net.eval().requires_grad_(False)


def resnet18_trunk(weights: str | None) -> tuple[nn.Module, int]:
    """torchvision's ResNet18 up to the global average pool (F = 512), frozen.

    Args:
        weights: a local state_dict file (torchvision's key names); None downloads the
            ImageNet weights through torchvision (needs internet).

    Raises:
        MissingExtra: torchvision is not installed (or does not import with this torch).
        CheckpointError: the weights file is missing or does not fit ResNet18.
    """
    try:
        import torchvision  # type: ignore[import-not-found]  # noqa: F401
        from torchvision.models import (  # type: ignore[import-not-found]
            ResNet18_Weights,
            resnet18,
        )
    except Exception as err:  # ImportError, or a torchvision built for another torch
        raise MissingExtra("torchvision", "resnet", "the ResNet18 encoder") from err
    if weights is None:
        net = resnet18(weights=ResNet18_Weights.IMAGENET1K_V1)
    else:
        path = Path(weights)
        if not path.is_file():
            raise CheckpointError(f"encoder weights {path} do not exist")
        net = resnet18(weights=None)
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            net.load_state_dict(state)
        except Exception as err:
            raise CheckpointError(f"encoder weights {path} are not a ResNet18 state_dict: "
                                  f"{err}") from err
    net.fc = nn.Identity()  # type: ignore[assignment]
    return net.eval().requires_grad_(False), 512


class _ResNetInput(nn.Module):
    """uint8 (B, N, N, 3) -> ImageNet-normalised float (B, 3, S, S)."""

    mean: torch.Tensor
    std: torch.Tensor

    def __init__(self, size_px: int) -> None:
        super().__init__()
        self.size_px = size_px
        self.register_buffer("mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1))
        self.register_buffer("std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images_to_float(images)
        if x.shape[-1] != self.size_px:
            x = nn.functional.interpolate(x, size=(self.size_px, self.size_px),
                                          mode="bilinear", align_corners=False)
        return (x - self.mean) / self.std


class FrozenEncoder:
    """A frozen image encoder with a per-process feature cache.

    ``encode(images)`` runs the network; ``features(image, key)`` looks the view up
    by ``key = (task_index, cell, alt_m)`` and encodes it only the first time.
    """

    def __init__(self, net: nn.Module, out_dim: int, spec: dict[str, Any]) -> None:
        self.net = net.eval().requires_grad_(False)
        self.out_dim = out_dim
        self.spec = spec
        self._cache: dict[CacheKey, torch.Tensor] = {}
        self.hits = 0
        self.misses = 0

    @torch.no_grad()
    def encode(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """uint8 (B, N, N, 3) -> float (B, F)."""
        x = torch.as_tensor(images)
        if x.dim() == 3:
            x = x.unsqueeze(0)
        return self.net(x)

    def features(self, image: np.ndarray, key: CacheKey | None = None) -> torch.Tensor:
        """(F,) features of one (N, N, 3) view, cached under ``key`` when given."""
        if key is None:
            return self.encode(image)[0]
        feat = self._cache.get(key)
        if feat is None:
            self.misses += 1
            feat = self._cache[key] = self.encode(image)[0]
        else:
            self.hits += 1
        return feat

    def clear(self) -> None:
        self._cache.clear()

    def __len__(self) -> int:
        return len(self._cache)


def cache_key(info: dict[str, Any], *, target: bool = False) -> CacheKey:
    """The feature-cache key of the current view (or of the target view) from an env info."""
    cell = info["target_cell"] if target else info["cell"]
    key = (int(info["task_index"]), (int(cell[0]), int(cell[1])), float(info["alt_m"]))
    if "augment_variant" in info:  # geonav.wrappers.ImageryRandomisation: one view per variant
        return (*key, int(info["augment_variant"]))
    return key


def _file_sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def build_frozen_encoder(cfg: NetConfig) -> FrozenEncoder | None:
    """The frozen encoder a config asks for, or None for the trainable CNN."""
    if cfg.encoder == "cnn":
        return None
    if cfg.encoder == "random":
        cnn = random_cnn(cfg.obs_size_px, cfg.random_encoder_seed, cfg.input_norm)
        return FrozenEncoder(cnn, cnn.out_dim, {"kind": "random", "seed": cfg.random_encoder_seed,
                                                "input_norm": cfg.input_norm})
    if cfg.encoder == "resnet18":
        trunk, dim = resnet18_trunk(cfg.encoder_weights)
        net = nn.Sequential(_ResNetInput(224), trunk)
        spec: dict[str, Any] = {"kind": "resnet18", "weights": cfg.encoder_weights}
        if cfg.encoder_weights is not None:
            spec["weights_sha256"] = _file_sha256(cfg.encoder_weights)
        return FrozenEncoder(net, dim, spec)
    raise ConfigError(f"unknown encoder {cfg.encoder!r}")


def feature_dim(cfg: NetConfig) -> int:
    """Width F of the encoder output for a config (without building ResNet)."""
    if cfg.encoder in ("cnn", "random"):
        return SmallCNN(cfg.obs_size_px).out_dim
    return 512
