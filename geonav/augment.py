"""Imagery randomisation: seeded variants of the rendered views (issue 12, item 5(b)).

Against the urban -> wild failure of transfer, meta-training can see each view under
``variants`` randomised appearances: colour (brightness, contrast), a season-like hue
rotation, blur and a GSD jitter. A variant is a fixed set of transform parameters drawn
from ``(seed, k)`` alone, so variant k is the same in every process, every run with that
seed and whatever the number of variants; the transforms are pure functions of the
(N, N, 3) uint8 view and the parameters, so the observation tables of
:class:`geonav.vecenv.LatticeVecEnv` and the Gymnasium wrapper
:class:`geonav.wrappers.ImageryRandomisation` give the same pixels for the same variant.

The transforms, applied in this order to the view in float32 (0..255):

1. GSD jitter, factor ``s`` uniform in ``[1 - gsd_jitter, 1 + gsd_jitter]``: the view is
   rescaled about its centre (``cv2.warpAffine``, bilinear, border reflected), so it shows
   a ground footprint ``1 / s`` times the camera's (s > 1: as from lower down, a finer GSD;
   s < 1: a wider footprint whose outer band of ``(1 - s) / 2`` of the side is reflected).
2. Gaussian blur, sigma uniform in ``[0, blur_px]`` pixels of the view (``cv2.GaussianBlur``;
   below 0.05 px it is skipped as a no-op).
3. Hue rotation by ``h`` uniform in ``[-hue_deg, hue_deg]`` degrees: the chroma plane
   (Cr, Cb of ITU-R BT.601, OpenCV's ``COLOR_RGB2YCrCb``) is rotated and the luma kept,
   one 3 x 3 colour matrix (``cv2.transform``). Greens turn yellow-brown one way and
   blue-green the other: a season-like change that keeps the brightness structure.
4. Contrast, factor ``1 + c`` with ``c`` uniform in ``[-contrast, contrast]``, about the
   view's mean luma.
5. Brightness, gain ``1 + b`` with ``b`` uniform in ``[-brightness, brightness]``.

Then rounding and clipping to uint8. With every magnitude 0 each variant is the identity.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from geonav.errors import ConfigError

# ITU-R BT.601 as OpenCV's RGB -> YCrCb, centred: Y, Cr = 0.713 (R - Y), Cb = 0.564 (B - Y).
_Y = np.array([0.299, 0.587, 0.114])
_YCRCB = np.stack([_Y, 0.713 * (np.array([1.0, 0.0, 0.0]) - _Y),
                   0.564 * (np.array([0.0, 0.0, 1.0]) - _Y)])
_LUMA = _YCRCB[0]
_TAG = 0x67656F61  # "geoa": keeps the variant streams apart from other seeded draws


@dataclass(frozen=True)
class AugmentConfig:
    """Imagery randomisation settings (a stage's ``augment = {...}`` table).

    Attributes:
        variants: K, the number of randomised variants of every view (>= 1).
        keep_clean: the unmodified imagery is one more variant (number 0), drawn like the
            others, so the tables hold K + 1 copies; False: only the K randomised ones.
        brightness: maximum relative gain change (0.2: gains in [0.8, 1.2]); in [0, 1).
        contrast: maximum relative contrast change about the mean luma; in [0, 1).
        hue_deg: maximum hue rotation in degrees (season-like shifts); in [0, 180].
        blur_px: maximum Gaussian blur sigma in view pixels; in [0, 5].
        gsd_jitter: maximum relative rescale of the view (0.1: a footprint 0.91-1.11x the
            camera's); in [0, 0.5].
        seed: seed of the variants' parameters (variant k depends on (seed, k) only).
    """

    variants: int = 8
    keep_clean: bool = True
    brightness: float = 0.2
    contrast: float = 0.2
    hue_deg: float = 15.0
    blur_px: float = 1.0
    gsd_jitter: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        limits = {"brightness": (0.0, 1.0, False), "contrast": (0.0, 1.0, False),
                  "hue_deg": (0.0, 180.0, True), "blur_px": (0.0, 5.0, True),
                  "gsd_jitter": (0.0, 0.5, True)}
        for name, (lo, hi, closed) in limits.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ConfigError(f"augment {name} = {v!r}: expected a number")
            if not (lo <= v <= hi if closed else lo <= v < hi):
                raise ConfigError(f"augment {name} = {v!r}: must lie in [{lo:g}, {hi:g}"
                                  f"{']' if closed else ')'}")
        for name in ("variants", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int):
                raise ConfigError(f"augment {name} = {v!r}: expected an integer")
        if not 1 <= self.variants <= 64:
            raise ConfigError(f"augment variants = {self.variants}: must lie in 1..64 (each "
                              "variant is one more copy of the observation table)")
        if not isinstance(self.keep_clean, bool):
            raise ConfigError(f"augment keep_clean = {self.keep_clean!r}: expected true/false")

    @property
    def n_variants(self) -> int:
        """Copies of every view: K, plus the clean one with ``keep_clean``."""
        return self.variants + int(self.keep_clean)

    @property
    def is_identity(self) -> bool:
        return not (self.brightness or self.contrast or self.hue_deg or self.blur_px
                    or self.gsd_jitter)

    def params(self, variant: int) -> VariantParams:
        """The transform parameters of variant ``variant`` (0..n_variants-1)."""
        if not 0 <= variant < self.n_variants:
            raise ConfigError(f"augment variant {variant} out of range "
                              f"0..{self.n_variants - 1}")
        if self.keep_clean:
            if variant == 0:
                return VariantParams()
            k = variant
        else:
            k = variant + 1
        # one stream per (seed, k); five draws always, so one magnitude never moves another
        u = np.random.default_rng(np.random.SeedSequence([_TAG, self.seed, k])).uniform(
            -1.0, 1.0, 5)
        return VariantParams(brightness=float(u[0] * self.brightness),
                             contrast=float(u[1] * self.contrast),
                             hue_deg=float(u[2] * self.hue_deg),
                             blur_sigma_px=float((u[3] + 1.0) / 2.0 * self.blur_px),
                             scale=float(1.0 + u[4] * self.gsd_jitter))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: Any, where: str = "augment") -> AugmentConfig:
        """Validated from a mapping (TOML table or JSON object); typed errors name the key."""
        if isinstance(d, AugmentConfig):
            return d
        if not isinstance(d, dict):
            raise ConfigError(f"{where} must be a table such as {{variants = 8, brightness "
                              f"= 0.2}}, got {type(d).__name__} {d!r}")
        known = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(known))
        if unknown:
            raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {known}")
        try:
            return cls(**d)
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from err


def parse_augment(text: str) -> AugmentConfig:
    """An :class:`AugmentConfig` from a command-line string: a JSON object
    (``'{"variants": 8, "hue_deg": 15}'``) or comma-separated ``key=value`` pairs
    (``variants=8,hue_deg=15,keep_clean=false``); unnamed keys keep their defaults."""
    text = text.strip()
    if text.startswith("{"):
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as err:
            raise ConfigError(f"--augment {text!r} is not valid JSON: {err}") from err
        return AugmentConfig.from_dict(obj, "--augment")
    d: dict[str, Any] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        key, sep, value = item.partition("=")
        if not sep:
            raise ConfigError(f"--augment item {item!r}: expected key=value (for example "
                              "variants=8,hue_deg=15) or a JSON object")
        try:
            d[key.strip()] = json.loads(value.strip())
        except json.JSONDecodeError as err:
            raise ConfigError(f"--augment {key.strip()} = {value.strip()!r}: not a number "
                              "or true/false") from err
    return AugmentConfig.from_dict(d, "--augment")


@dataclass(frozen=True)
class VariantParams:
    """The drawn parameters of one variant (identity by default)."""

    brightness: float = 0.0
    """relative gain change b: pixels times (1 + b)."""
    contrast: float = 0.0
    """relative contrast change c: (x - mean luma) times (1 + c)."""
    hue_deg: float = 0.0
    """rotation of the (Cr, Cb) chroma plane, degrees."""
    blur_sigma_px: float = 0.0
    """Gaussian blur sigma, view pixels."""
    scale: float = 1.0
    """GSD jitter: the view magnified by this factor about its centre."""

    @property
    def is_identity(self) -> bool:
        return (self.brightness == 0 and self.contrast == 0 and self.hue_deg == 0
                and self.blur_sigma_px < 0.05 and self.scale == 1.0)


def hue_matrix(hue_deg: float) -> np.ndarray:
    """(3, 3) float64 RGB -> RGB matrix rotating the BT.601 chroma plane by ``hue_deg``
    and keeping the luma row: ``luma @ M == luma``."""
    t = math.radians(hue_deg)
    rot = np.array([[1.0, 0.0, 0.0],
                    [0.0, math.cos(t), -math.sin(t)],
                    [0.0, math.sin(t), math.cos(t)]])
    return np.linalg.inv(_YCRCB) @ rot @ _YCRCB


def augment_image(image: np.ndarray, p: VariantParams) -> np.ndarray:
    """One (N, N, 3) uint8 view under variant ``p`` (see the module docstring); a new
    array, equal to the input for the identity."""
    if p.is_identity:
        return np.array(image, np.uint8, copy=True)
    x: Any = np.asarray(image, np.float32)
    n_h, n_w = x.shape[:2]
    if p.scale != 1.0:
        cx, cy = (n_w - 1) / 2.0, (n_h - 1) / 2.0
        m = np.array([[p.scale, 0.0, (1.0 - p.scale) * cx],
                      [0.0, p.scale, (1.0 - p.scale) * cy]], np.float64)
        x = cv2.warpAffine(x, m, (n_w, n_h), flags=cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REFLECT_101)
    if p.blur_sigma_px >= 0.05:
        x = cv2.GaussianBlur(x, (0, 0), p.blur_sigma_px, borderType=cv2.BORDER_REFLECT_101)
    if p.hue_deg != 0.0:
        x = cv2.transform(x, hue_matrix(p.hue_deg).astype(np.float32))
    if p.contrast != 0.0:
        mean = float((x.reshape(-1, 3) @ _LUMA.astype(np.float32)).mean())
        x = (x - mean) * np.float32(1.0 + p.contrast) + np.float32(mean)
    if p.brightness != 0.0:
        x = x * np.float32(1.0 + p.brightness)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def augment_images(images: np.ndarray, p: VariantParams) -> np.ndarray:
    """(n, N, N, 3) uint8 views under variant ``p`` (a new array)."""
    out = np.empty_like(images, dtype=np.uint8)
    for i in range(len(images)):
        out[i] = augment_image(images[i], p)
    return out


__all__ = ["AugmentConfig", "VariantParams", "augment_image", "augment_images",
           "hue_matrix", "parse_augment"]
