"""Image encoders: a small trainable CNN, a frozen random CNN, a frozen ResNet18 and the
parameter-free view correlation.

Trainable encoders live inside the actor-critic (their parameters are learned);
frozen ones live outside it, in a :class:`FrozenEncoder` with a feature cache
keyed by (task, cell, altitude), so each view is encoded once per process; the task
part names the scene and the task's content, so envs may share one encoder.

The correlation encoder (``encoder='corr'``) is *pairwise*: a view's features are its
normalised cross-correlation with the episode's target view at every shift within
``corr_radius`` (:func:`view_correlation`), so they say where the target's imagery lies
in the current view, in the same way on any scene. Its :class:`FrozenEncoder` encodes
each image to a grey half-resolution map (``encode``) and combines a view's map with its
target's (``combine``); ``features(image, key, target=...)`` does both. The target
view's own features are its autocorrelation.

Images enter as uint8 ``(B, N, N, 3)`` arrays/tensors (the env's layout) and
leave as float features ``(B, F)``.
"""

from __future__ import annotations

import functools
import hashlib
import logging
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from geonav.errors import CheckpointError, ConfigError, MissingExtra
from geonav.policy.config import CNN_KINDS, NetConfig

log = logging.getLogger(__name__)

CacheKey = (tuple[int | str, tuple[int, int], float]
            | tuple[int | str, tuple[int, int], float, int])
"""(task key or index, cell, altitude), plus the imagery variant when the env is randomised."""

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
    """The trainable image encoder: (B, N, N, 3) uint8 -> (B, F).

    ``kind='small'``: two strided convolutions (Mnih et al. 2013 sizes): at 84 px 8x8/4 ->
    16x20x20, 4x4/2 -> 32x9x9, F = 2592; at 64 px F = 1152. ``kind='nature'``: the three
    convolutions of Mnih et al. 2015 (SB3's NatureCNN without its linear layer, which the
    actor-critic's view embeddings play): 8x8/4 -> 32, 4x4/2 -> 64, 3x3/1 -> 64; at 64 px
    F = 1024, at 84 px F = 3136.
    """

    def __init__(self, obs_size_px: int, input_norm: str = "center", kind: str = "small"
                 ) -> None:
        super().__init__()
        if kind not in CNN_KINDS:
            raise ConfigError(f"cnn must be one of {CNN_KINDS}, not {kind!r}")
        self.input_norm = input_norm
        wide = kind == "nature"
        self.conv1 = nn.Conv2d(3, 32 if wide else 16, kernel_size=8, stride=4)
        self.conv2 = nn.Conv2d(self.conv1.out_channels, 64 if wide else 32, kernel_size=4,
                               stride=2)
        self.conv3 = nn.Conv2d(64, 64, kernel_size=3, stride=1) if wide else None
        s = (obs_size_px - 8) // 4 + 1
        s = (s - 4) // 2 + 1
        if wide:
            s = s - 2
        if s < 1:
            raise ConfigError(f"obs_size_px {obs_size_px} is too small for the {kind} CNN "
                              f"(>= {36 if wide else 16})")
        self.out_dim = (64 if wide else 32) * s * s

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images_to_float(images, self.input_norm, self.conv1.weight.dtype) \
            if images.dtype == torch.uint8 else images
        x = torch.relu(self.conv1(x))
        x = torch.relu(self.conv2(x))
        if self.conv3 is not None:
            x = torch.relu(self.conv3(x))
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


class GreyMap(nn.Module):
    """The per-image stage of the correlation encoder: uint8 (B, N, N, 3) -> the centred
    grey view, 2 x 2 mean-pooled, flattened (B, (N // 2)^2)."""

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        g = images_to_float(images, "center").mean(1, keepdim=True)
        return F.avg_pool2d(g, 2).flatten(1)


def view_correlation(a: torch.Tensor, b: torch.Tensor, side: int, radius: int,
                     chunk: int = 512) -> torch.Tensor:
    """Normalised cross-correlation of square maps at every shift within ``radius``.

    Args:
        a: (M, side * side) maps of the current views; b: the same of their targets.
    Returns:
        (M, (2 * radius + 1)^2): entry (i, j) (row-major, shifts -radius..radius) is the mean
        over the overlap of a[y, x] * b[y + i - radius, x + j - radius], each map first made
        zero-mean and unit-RMS; 1 where b is a shifted a, about 0 for unrelated imagery.
    """
    r = radius
    d = torch.arange(-r, r + 1, dtype=a.dtype)
    overlap = (side - d.abs())[:, None] * (side - d.abs())[None, :]
    outs = []
    for i in range(0, a.shape[0], chunk):
        x = a[i:i + chunk].reshape(-1, 1, side, side)
        y = b[i:i + chunk].reshape(-1, 1, side, side)
        x = x - x.mean((2, 3), keepdim=True)
        y = y - y.mean((2, 3), keepdim=True)
        x = x / (x.pow(2).mean((2, 3), keepdim=True).sqrt() + 1e-6)
        y = y / (y.pow(2).mean((2, 3), keepdim=True).sqrt() + 1e-6)
        m = x.shape[0]
        yp = F.pad(y, (r, r, r, r)).reshape(1, m, side + 2 * r, side + 2 * r)
        out = F.conv2d(yp, x, groups=m).reshape(m, 2 * r + 1, 2 * r + 1)
        outs.append((out / overlap).flatten(1))
    return torch.cat(outs) if outs else a.new_zeros((0, (2 * r + 1) ** 2))


class FrozenEncoder:
    """A frozen image encoder with a per-process feature cache.

    ``encode(images)`` runs the network; ``features(image, key)`` looks the view up
    by ``key = (task, cell, alt_m)`` (``cache_key``: the task is its env's ``task_key``,
    which names the scene, so one encoder serves several envs) and encodes it only the
    first time. A
    *pairwise* encoder (``pair`` given: the correlation encoder) turns ``encode``'s maps
    of a view and of its target into the features (``combine``), so ``features`` needs
    the target image; the cache key (task, cell, altitude) fixes the target.
    """

    def __init__(self, net: nn.Module, out_dim: int, spec: dict[str, Any],
                 pair: Any = None) -> None:
        self.net = net.eval().requires_grad_(False)
        self.out_dim = out_dim
        self.spec = spec
        self.pair = pair
        self._cache: dict[CacheKey, torch.Tensor] = {}
        self.hits = 0
        self.misses = 0

    @property
    def pairwise(self) -> bool:
        """True when a view's features depend on its target view too."""
        return self.pair is not None

    @torch.no_grad()
    def encode(self, images: np.ndarray | torch.Tensor) -> torch.Tensor:
        """uint8 (B, N, N, 3) -> float (B, F) (a pairwise encoder's per-image maps)."""
        x = torch.as_tensor(images)
        if x.dim() == 3:
            x = x.unsqueeze(0)
        return self.net(x)

    @torch.no_grad()
    def combine(self, maps: torch.Tensor, target_maps: torch.Tensor) -> torch.Tensor:
        """Features from ``encode``'s output of views and of their targets (row by row);
        the maps themselves for an encoder that is not pairwise."""
        return maps if self.pair is None else self.pair(maps, target_maps)

    def features(self, image: np.ndarray, key: CacheKey | None = None,
                 target: np.ndarray | None = None) -> torch.Tensor:
        """(F,) features of one (N, N, 3) view, cached under ``key`` when given; a pairwise
        encoder needs the episode's ``target`` image."""
        feat = self._cache.get(key) if key is not None else None
        if feat is not None:
            self.hits += 1
            return feat
        if self.pair is not None:
            if target is None:
                raise ValueError("the correlation encoder compares a view with its target: "
                                 "pass target=")
            feat = self.combine(self.encode(image), self.encode(target))[0]
        else:
            feat = self.encode(image)[0]
        if key is not None:
            self.misses += 1
            self._cache[key] = feat
        return feat

    def clear(self) -> None:
        self._cache.clear()

    def __len__(self) -> int:
        return len(self._cache)


def cache_key(info: dict[str, Any], *, target: bool = False) -> CacheKey:
    """The feature-cache key of the current view (or of the target view) from an env info.

    The current view is the one at ``info["view_cell"]`` when the info has it (view
    ablation, :func:`geonav.policy.evaluation.ablated_observation`: the image shown is
    another cell's), else at ``info["cell"]``."""
    cell = info["target_cell"] if target else info.get("view_cell", info["cell"])
    # the task's key names its scene, lattice, target and camera, so one encoder serves
    # several envs; infos without it (hand-made ones) fall back to the task's index
    task = info.get("task_key", int(info["task_index"]))
    key = (task, (int(cell[0]), int(cell[1])), float(info["alt_m"]))
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
    if cfg.encoder == "corr":
        side, r = cfg.obs_size_px // 2, cfg.corr_radius
        return FrozenEncoder(GreyMap(), (2 * r + 1) ** 2, {"kind": "corr", "radius": r},
                             pair=functools.partial(view_correlation, side=side, radius=r))
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
        return SmallCNN(cfg.obs_size_px, kind=cfg.cnn if cfg.encoder == "cnn" else "small"
                        ).out_dim
    if cfg.encoder == "corr":
        return (2 * cfg.corr_radius + 1) ** 2
    return 512
