"""Tests for geonav.tiles.synth: contract, determinism, heights, looks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from geonav.errors import ConfigError
from geonav.tiles.synth import KINDS, SynthImage, synthesize

# Small scenes keep the suite fast: 400 m at 1 m/px is 400x400 pixels.
SIZE_M = 400.0
GSD_M = 1.0


@pytest.fixture(scope="module")
def scenes() -> dict[str, SynthImage]:
    """One small scene per kind, shared by the read-only tests."""
    return {kind: synthesize(kind, SIZE_M, GSD_M, seed=3) for kind in KINDS}


@pytest.fixture(scope="module")
def fine_residential() -> SynthImage:
    """A residential scene at the native 0.25 m/px, for texture and object checks."""
    return synthesize("residential", 150.0, 0.25, seed=5)


def test_shapes_dtypes_and_fields(scenes: dict[str, SynthImage]) -> None:
    for kind, im in scenes.items():
        assert im.rgb.shape == (400, 400, 3)
        assert im.rgb.dtype == np.uint8
        assert im.height_m.shape == (400, 400)
        assert im.height_m.dtype == np.float32
        assert im.gsd_m == GSD_M
        assert im.kind == kind
        assert im.seed == 3
        assert np.isfinite(im.height_m).all()
        assert im.height_m.min() >= 0.0


def test_side_follows_size_and_gsd() -> None:
    im = synthesize("wild", 120.0, 0.5, seed=1)
    assert im.rgb.shape == (240, 240, 3)
    assert im.height_m.shape == (240, 240)


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_same_scene(kind: str) -> None:
    a = synthesize(kind, 200.0, 1.0, seed=11)
    b = synthesize(kind, 200.0, 1.0, seed=11)
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.height_m, b.height_m)


@pytest.mark.parametrize("kind", KINDS)
def test_different_seed_different_scene(kind: str) -> None:
    a = synthesize(kind, 200.0, 1.0, seed=11)
    b = synthesize(kind, 200.0, 1.0, seed=12)
    assert np.mean(a.rgb != b.rgb) > 0.5
    assert not np.array_equal(a.height_m, b.height_m)


def test_kinds_do_not_share_random_streams() -> None:
    a = synthesize("residential", 200.0, 1.0, seed=0)
    b = synthesize("campus", 200.0, 1.0, seed=0)
    assert not np.array_equal(a.height_m, b.height_m)


def test_progress_reports_fractions_up_to_one() -> None:
    seen: list[float] = []
    synthesize("campus", 150.0, 1.0, seed=0, progress=seen.append)
    assert seen[0] == 0.0
    assert seen[-1] == 1.0
    assert all(0.0 <= f <= 1.0 for f in seen)
    assert seen == sorted(seen)


def test_residential_heights(scenes: dict[str, SynthImage]) -> None:
    h = scenes["residential"].height_m
    assert (h == 0).mean() > 0.4, "most of a residential scene is ground"
    assert (h > 40.0).any(), "a residential scene has a tower"
    assert h.max() < 100.0
    houses = ((h >= 5.0) & (h <= 12.0)).mean()
    assert houses > 0.05, "house roofs and trees between 5 and 12 m"
    cars = ((h > 1.2) & (h < 1.8)).sum()
    assert cars > 50, "cars of about 1.5 m"


def test_campus_heights(scenes: dict[str, SynthImage]) -> None:
    h = scenes["campus"].height_m
    assert (h > 40.0).any(), "a campus scene has a tower"
    assert ((h >= 10.0) & (h <= 30.0)).mean() > 0.05, "campus buildings 10-30 m"


def test_wild_heights(scenes: dict[str, SynthImage]) -> None:
    h = scenes["wild"].height_m
    assert h.max() <= 30.0, "no tall structures in wild land"
    assert (h >= 8.0).mean() > 0.1, "forest canopy 8-25 m"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_few_landmarks_above_75_m(seed: int) -> None:
    for kind in ("residential", "campus"):
        h = synthesize(kind, 600.0, 2.0, seed=seed).height_m
        tall = (h > 75.0).astype(np.uint8)
        n_blobs, _ = cv2.connectedComponents(tall)
        assert n_blobs - 1 <= 2
        assert h.max() < 100.0


def test_kinds_differ_in_colour(scenes: dict[str, SynthImage]) -> None:
    means = {kind: im.rgb.reshape(-1, 3).mean(axis=0) for kind, im in scenes.items()}
    from geonav.tiles.synth import MIXED_BANDS  # the base kinds (mixed is made of them)

    for a in MIXED_BANDS:
        for b in MIXED_BANDS:
            if a < b:
                assert np.abs(means[a] - means[b]).max() > 4.0, (a, b, means[a], means[b])

    # Wild land is greener (less grey) than built-up land.
    def greyness(im: SynthImage) -> float:
        rgb = im.rgb.astype(np.float32)
        return float((rgb.max(axis=2) - rgb.min(axis=2) < 12).mean())

    assert greyness(scenes["wild"]) < greyness(scenes["residential"])
    assert greyness(scenes["wild"]) < greyness(scenes["campus"])


@pytest.mark.parametrize("kind", KINDS)
def test_textured_everywhere(kind: str, scenes: dict[str, SynthImage]) -> None:
    grey = scenes[kind].rgb.astype(np.float32).mean(axis=2)
    patches = grey.reshape(20, 20, 20, 20).swapaxes(1, 2).reshape(400, -1)
    stds = patches.std(axis=1)
    assert np.median(stds) > 8.0
    assert stds.min() > 1.0, "no flat 20x20 m patch anywhere"


def test_textured_at_native_resolution(fine_residential: SynthImage) -> None:
    grey = fine_residential.rgb.astype(np.float32).mean(axis=2)
    n = grey.shape[0] // 30 * 30
    patches = grey[:n, :n].reshape(n // 30, 30, n // 30, 30).swapaxes(1, 2).reshape(-1, 900)
    # Every 7.5 m patch has texture, not a flat fill.
    assert patches.std(axis=1).min() > 1.5


def test_no_two_views_identical(fine_residential: SynthImage) -> None:
    """84x84 views at different places differ (locations must be recognisable)."""
    rgb = fine_residential.rgb.astype(np.float32)
    views = [rgb[r : r + 84, c : c + 84] for r in range(0, 500, 120) for c in range(0, 500, 120)]
    for i in range(len(views)):
        for j in range(i + 1, len(views)):
            assert np.abs(views[i] - views[j]).mean() > 5.0


def test_shadows_fall_away_from_the_sun(fine_residential: SynthImage) -> None:
    """Next to raised objects, the side away from the sun is darker."""
    h = fine_residential.height_m
    grey = fine_residential.rgb.astype(np.float32).mean(axis=2)
    raised = h > 3.0
    ground = h == 0.0
    # Sun to the east-south-east: shadows fall west-north-west of objects.
    west = np.zeros_like(raised)
    west[:, :-8] = raised[:, 8:]
    east = np.zeros_like(raised)
    east[:, 8:] = raised[:, :-8]
    shadowed_side = grey[ground & west & ~east].mean()
    sunny_side = grey[ground & east & ~west].mean()
    assert shadowed_side < 0.8 * sunny_side


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": "desert"}, "residential, campus, wild"),
        ({"kind": "wild", "size_m": 99.0}, "size_m"),
        ({"kind": "wild", "size_m": float("nan")}, "size_m"),
        ({"kind": "wild", "gsd_m": 0.02}, "gsd_m"),
        ({"kind": "wild", "gsd_m": 5.5}, "gsd_m"),
        ({"kind": "wild", "gsd_m": 0.0}, "gsd_m"),
        ({"kind": "wild", "size_m": 1e6, "gsd_m": 0.1}, "px per side"),
        ({"kind": "wild", "seed": -1}, "seed"),
    ],
)
def test_bad_arguments_raise_config_error(kwargs: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        synthesize(**kwargs)


def test_coarsest_gsd_works() -> None:
    im = synthesize("campus", 500.0, 5.0, seed=2)
    assert im.rgb.shape == (100, 100, 3)


def test_mixed_scene_is_the_three_kinds_in_bands(scenes: dict[str, SynthImage]) -> None:
    """Each third of a mixed scene, west to east, is that band of the whole scene of its
    kind with the same size, GSD and seed, pixels and heights alike."""
    from geonav.tiles.synth import MIXED_BANDS

    mixed = scenes["mixed"]
    cuts = np.linspace(0, mixed.rgb.shape[1], len(MIXED_BANDS) + 1).round().astype(int)
    for kind, a, b in zip(MIXED_BANDS, cuts[:-1], cuts[1:], strict=True):
        np.testing.assert_array_equal(mixed.rgb[:, a:b], scenes[kind].rgb[:, a:b])
        np.testing.assert_array_equal(mixed.height_m[:, a:b], scenes[kind].height_m[:, a:b])
    fractions: list[float] = []
    synthesize("mixed", 120.0, 1.0, seed=1, progress=fractions.append)
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
