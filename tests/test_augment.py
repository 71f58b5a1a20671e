"""Imagery randomisation: variants, transforms, the vecenv tables and the Gymnasium wrapper."""

from __future__ import annotations

import argparse
import dataclasses
import json

import cv2
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from geonav.augment import AugmentConfig, VariantParams, augment_image, parse_augment
from geonav.camera import Camera
from geonav.env import GeoNavEnv
from geonav.errors import ConfigError
from geonav.tasks import NavTask, TaskSet
from geonav.testing import textured_scene, tiny_taskset
from geonav.vecenv import LatticeVecEnv
from geonav.wrappers import ImageryRandomisation

ZERO = dict(brightness=0.0, contrast=0.0, hue_deg=0.0, blur_px=0.0, gsd_jitter=0.0)
LUMA = np.array([0.299, 0.587, 0.114])


@pytest.fixture(scope="module")
def two_task_env(scene):
    t1 = NavTask("a", "scene", (-45.0, -45.0, 45.0, 45.0), 15.0, 15.0, (5, 5), 12)
    t2 = NavTask("b", "scene", (-90.0, -30.0, 0.0, 60.0), 15.0, 15.0, (0, 2), 9)
    return GeoNavEnv(scene, TaskSet(scene.name, scene.scene_id, [t1, t2]),
                     camera=Camera(24, 90.0))


@pytest.fixture(scope="module")
def view(scene):
    """A 64 px textured view of the test scene."""
    env = GeoNavEnv(scene, tiny_taskset(scene), camera=Camera(64, 90.0))
    return env.observation_at(0, (1, 2))


def _luma(img):
    return img.astype(np.float64) @ LUMA


def test_variants_are_seeded_and_independent_of_their_number():
    a, b = AugmentConfig(variants=4, seed=3), AugmentConfig(variants=9, seed=3)
    assert [a.params(k) for k in range(5)] == [b.params(k) for k in range(5)]
    assert a.params(0) == VariantParams()  # keep_clean: variant 0 is the imagery itself
    assert len({a.params(k) for k in range(1, 5)}) == 4
    assert AugmentConfig(seed=4).params(1) != a.params(1)
    no_clean = AugmentConfig(variants=4, seed=3, keep_clean=False)
    assert no_clean.n_variants == 4 and no_clean.params(0) == a.params(1)
    for k in range(1, 5):
        p = a.params(k)
        assert abs(p.brightness) <= 0.2 and abs(p.contrast) <= 0.2 and abs(p.hue_deg) <= 15
        assert 0 <= p.blur_sigma_px <= 1.0 and 0.9 <= p.scale <= 1.1
    # one magnitude at zero leaves the others' draws alone
    assert AugmentConfig(variants=4, seed=3, hue_deg=0.0).params(2).brightness == \
        a.params(2).brightness


def test_all_magnitudes_zero_is_the_identity(view, two_task_env):
    cfg = AugmentConfig(variants=3, **ZERO)
    assert cfg.is_identity
    for k in range(cfg.n_variants):
        np.testing.assert_array_equal(augment_image(view, cfg.params(k)), view)
    venv = LatticeVecEnv(two_task_env, 2, augment=cfg)
    table = venv.image_table()
    c = venv.n_cells
    assert table.shape[0] == 4 * c
    for k in range(1, 4):
        np.testing.assert_array_equal(table[k * c:(k + 1) * c], table[:c])


def test_each_transform_changes_what_it_should(view):
    lum = _luma(view)
    # hue: chroma rotates, luma stays (up to rounding and a little clipping)
    hue = augment_image(view, VariantParams(hue_deg=40.0))
    assert np.abs(_luma(hue) - lum).mean() < 1.0
    assert np.abs(hue.astype(float) - view).mean() > 3.0
    # blur: less high-frequency energy (the Laplacian), the mean kept
    blur = augment_image(view, VariantParams(blur_sigma_px=1.5))

    def hf(x):
        return float(np.abs(cv2.Laplacian(_luma(x), cv2.CV_64F)).mean())
    assert hf(blur) < 0.6 * hf(view)
    assert abs(_luma(blur).mean() - lum.mean()) < 1.0
    # brightness: a gain on every pixel
    bright = augment_image(view, VariantParams(brightness=-0.25))
    np.testing.assert_allclose(bright.astype(float), np.rint(view * 0.75), atol=1)
    # contrast: the luma spread scales, its mean stays
    flat = augment_image(view, VariantParams(contrast=-0.5))
    assert _luma(flat).std() == pytest.approx(0.5 * lum.std(), rel=0.03)
    assert _luma(flat).mean() == pytest.approx(lum.mean(), abs=1.0)


def test_gsd_jitter_rescales_the_view_about_its_centre():
    n = 65
    ramp = np.repeat(np.repeat(np.arange(n, dtype=np.float64)[None, :, None], n, 0), 3, 2)
    img = np.rint(ramp * 3).astype(np.uint8)        # column j holds 3 j
    out = augment_image(img, VariantParams(scale=1.25)).astype(np.float64)
    c = (n - 1) / 2
    cols = np.arange(n)
    # magnified 1.25x: column j shows what was at c + (j - c) / 1.25 (a smaller footprint)
    np.testing.assert_allclose(out[n // 2, 5:-5, 0], 3 * (c + (cols[5:-5] - c) / 1.25), atol=1)
    shrunk = augment_image(img, VariantParams(scale=0.8)).astype(np.float64)
    inner = slice(int(c - 20), int(c + 21))
    np.testing.assert_allclose(shrunk[n // 2, inner, 0], 3 * (c + (cols[inner] - c) / 0.8),
                               atol=1)


def test_bad_values_are_refused_with_the_key():
    for bad, match in ((dict(brightness=1.0), "brightness"), (dict(hue_deg=-1), "hue_deg"),
                       (dict(gsd_jitter=0.6), "gsd_jitter"), (dict(blur_px=float("nan")),
                                                              "blur_px"),
                       (dict(variants=0), "variants"), (dict(variants=2.5), "variants"),
                       (dict(contrast=True), "contrast"), (dict(keep_clean=1), "keep_clean")):
        with pytest.raises(ConfigError, match=match):
            AugmentConfig.from_dict(bad)
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['saturation'\]"):
        AugmentConfig.from_dict({"saturation": 0.1})
    with pytest.raises(ConfigError, match="must be a table"):
        AugmentConfig.from_dict(8)
    assert parse_augment("variants=3,hue_deg=20,keep_clean=false") == \
        AugmentConfig(variants=3, hue_deg=20, keep_clean=False)
    assert parse_augment('{"variants": 2, "seed": 5}') == AugmentConfig(variants=2, seed=5)
    for bad in ("variants", "variants=x", "{variants: 2}", "blur_px=9"):
        with pytest.raises(ConfigError, match="--augment"):
            parse_augment(bad)


def test_vecenv_tables_agree_with_the_wrapper(two_task_env):
    cfg = AugmentConfig(variants=3, seed=1)
    wrapped = ImageryRandomisation(two_task_env, cfg)
    venv = LatticeVecEnv(wrapped, 3)                  # picks the wrapper's config up
    assert venv.augment == cfg and venv.n_variants == 4
    table = venv.image_table()
    assert table.shape[0] == venv.n_views == 4 * venv.n_cells
    rng = np.random.default_rng(0)
    tasks = [0, 1, 1]
    starts = [two_task_env.start_cells(t)[0] for t in tasks]
    variants = [2, 3, 0]
    venv.reset(tasks=tasks, starts=starts, variants=variants)
    for s in range(3):
        obs, info = wrapped.reset(options={"task": tasks[s], "start_cell": starts[s],
                                           "variant": variants[s]})
        assert info["augment_variant"] == variants[s]
        np.testing.assert_array_equal(obs["target"], table[venv.target_index[s]])
        np.testing.assert_array_equal(obs["image"], table[venv.view_index[s]])
        one = LatticeVecEnv(wrapped, 1)
        one.reset(tasks=[tasks[s]], starts=[starts[s]], variants=[variants[s]])
        for _ in range(6):
            a = int(rng.integers(4))
            obs, _, te, tr, info = wrapped.step(a)
            res = one.step([a], autoreset=False)
            np.testing.assert_array_equal(obs["image"], table[res.final_view[0]])
            np.testing.assert_array_equal(obs["target"], table[one.target_index[0]])
            assert info["cell"] == tuple(one.cell[0])
            if te or tr:
                break
    # variants differ from the clean views, and episodes draw all of them
    c = venv.n_cells
    assert all(np.abs(table[k * c:(k + 1) * c].astype(int) - table[:c]).mean() > 1
               for k in range(1, 4))
    big = LatticeVecEnv(wrapped, 64)
    big.reset(seed=0)
    assert set(big.variant.tolist()) == {0, 1, 2, 3}
    assert big.info(0)["augment_variant"] == int(big.variant[0])


def test_bare_vecenv_is_unchanged(two_task_env):
    venv = LatticeVecEnv(two_task_env, 8)
    assert venv.augment is None and venv.n_views == venv.n_cells
    venv.reset(seed=0)
    assert not venv.variant.any() and "augment_variant" not in venv.info(0)


@pytest.mark.filterwarnings("ignore:.*is different from the unwrapped version")
def test_wrapper_is_a_seeded_gymnasium_env(scene):
    env = ImageryRandomisation(GeoNavEnv(scene, tiny_taskset(scene), camera=Camera(32, 90.0)),
                               {"variants": 5, "seed": 2})
    check_env(env, skip_render_check=True)

    def run(seed):
        out = [env.reset(seed=seed)[1]["augment_variant"]]
        out += [env.reset()[1]["augment_variant"] for _ in range(11)]
        return out

    first = run(7)
    assert first == run(7) and len(set(first)) > 2
    assert run(8) != first
    # the bare env's own draws are untouched: same starts as the unwrapped env
    bare = GeoNavEnv(scene, tiny_taskset(scene), camera=Camera(32, 90.0))
    assert env.reset(seed=3)[1]["cell"] == bare.reset(seed=3)[1]["cell"]
    with pytest.raises(ConfigError, match="variant 6 out of range"):
        env.reset(options={"variant": 6})
    from geonav.policy.encoders import cache_key

    _, info = env.reset(options={"variant": 4})
    assert cache_key(info)[-1] == 4 and len(cache_key(info)) == 4


def test_stage_option_is_validated_in_the_config():
    from geonav.experiments.config import parse_config

    def cfg(augment):
        return {"name": "t", "seeds": [0], "convergence": {"window": 10},
                "scenes": {"A": {"synthetic": "residential"}},
                "tasks": {"T": {"scene": "A"}},
                "stages": {"m": {"mode": "meta-train", "tasks": "T", "episodes": 10,
                                 "augment": augment}}}

    assert parse_config(cfg({"variants": 2, "hue_deg": 10})).stages["m"].options[
        "augment"] == {"variants": 2, "hue_deg": 10}
    parse_config(cfg(True))
    with pytest.raises(ConfigError, match=r"\[stages.m\] augment: augment hue_deg = 200"):
        parse_config(cfg({"hue_deg": 200}))
    with pytest.raises(ConfigError, match=r"\[stages.m\] augment: unknown key"):
        parse_config(cfg({"hue": 10}))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("aug")
    scene = textured_scene(size_m=300.0)
    scene.save(root / "scene")
    ts = tiny_taskset(scene, max_steps=10)
    dataclasses.replace(ts, camera=Camera(32, 90.0)).save(root / "tasks.json")
    return root


def test_augmented_meta_train_stage_runs_end_to_end(files):
    """A tiny meta-train unit with augment on the batched engine: the learner's frozen
    feature table holds every variant, and the unit's evaluation runs on clean imagery."""
    from geonav.experiments import stages
    from geonav.policy.engine import build_meta_trainer

    out = files / "unit"
    p = dict(stage="m", mode="meta-train", algo="savn", episodes=8, workers=1, seed=0,
             scene=str(files / "scene"), tasks=str(files / "tasks.json"),
             init_checkpoint=None, out_dir=str(out), eval_starts=3,
             convergence=dict(window=50, threshold=0.99, hold=0.99),
             options=dict(encoder="random", obs_size_px=32, eval_every=0,
                          augment={"variants": 2, "seed": 1}))
    res = stages.execute_stage(p)
    assert res["episodes"] >= 8 and 0.0 <= res["eval"]["greedy_sr"] <= 1.0
    assert len((out / "metrics.csv").read_text().splitlines()) >= 1 + 8
    # the trainer the stage built sees 3 copies of the table (clean + 2)
    from geonav.policy.config import NetConfig
    from geonav.policy.envs import EnvFactory
    from geonav.policy.meta_config import MetaConfig, base_config

    factory = EnvFactory(str(files / "scene"), str(files / "tasks.json"),
                         augment=AugmentConfig(variants=2, seed=1))
    t = build_meta_trainer("savn", "batched", factory, NetConfig(encoder="random",
                                                                  obs_size_px=32),
                           base_config("savn", {"episodes": 2}), MetaConfig(episodes=2),
                           out_dir=str(files / "direct"), tensorboard=False)
    t.train()
    assert t.venv.n_variants == 3
    assert t.table.shape[0] == 3 * t.venv.n_cells
    with pytest.raises(ConfigError, match=r"\[stages.m\] augment"):
        stages.execute_stage(dict(p, out_dir=str(files / "bad"),
                                  options=dict(p["options"], augment={"blur_px": -1})))


@pytest.mark.parametrize("per_step", [False, True])
def test_meta_isar_view_embeddings_read_the_episode_variant(files, tmp_path, monkeypatch,
                                                            per_step):
    """Batched meta-ISAR's per-window view embeddings (ViewBases) read each slot's views and
    target under its episode's imagery variant, the rows slot_indices() gives. Before, the
    per-window table of a small task (paper.toml's meta25_aug, shrunk) indexed past the
    clean rows and raised IndexError, and the target was always the clean view."""
    import torch

    from geonav.policy.batched import meta as meta_mod
    from geonav.policy.config import NetConfig
    from geonav.policy.engine import build_meta_trainer
    from geonav.policy.envs import EnvFactory
    from geonav.policy.meta_config import MetaConfig, base_config

    if per_step:  # the view embeddings per step, not as a table per window
        monkeypatch.setattr(meta_mod, "PRE_TABLE_VIEWS_PER_STEP", 0)
    factory = EnvFactory(str(files / "scene"), str(files / "tasks.json"),
                         augment=AugmentConfig(variants=2, seed=1))
    t = build_meta_trainer("isar", "batched", factory,
                           NetConfig(encoder="random", obs_size_px=32, hidden_size=16,
                                     lstm_size=16),
                           base_config("isar", {"episodes": 4}),
                           MetaConfig(episodes=4, workers=0, batch_tasks=2),
                           out_dir=str(tmp_path), tensorboard=False)
    t.train()
    venv = t.venv
    venv.reset(variants=[1, 2])
    phi, _, _ = t.task_parameters()
    views = t.view_bases(phi, np.arange(venv.n_slots))
    vi, ti = t.slot_indices()
    assert (vi >= venv.n_cells).all()  # not the clean rows
    w, b = phi["obs_embed.weight"].detach(), phi["obs_embed.bias"].detach()
    torch.testing.assert_close(
        views.obs(vi, False), torch.baddbmm(b.unsqueeze(1), t.table[vi].unsqueeze(1), w)
        .squeeze(1))
    w, b = phi["target_embed.weight"].detach(), phi["target_embed.bias"].detach()
    torch.testing.assert_close(
        views.target.detach(), torch.baddbmm(b.unsqueeze(1), t.table[ti].unsqueeze(1), w)
        .squeeze(1))


def test_cli_train_with_augment(files, tmp_path):
    from geonav.policy import cli

    parser = argparse.ArgumentParser()
    cli.add_parser(parser.add_subparsers(dest="command", required=True))
    base = ["train", "--algo", "a3c", "--scene", str(files / "scene"), "--tasks",
            str(files / "tasks.json"), "--out", str(tmp_path / "run"), "--obs-size", "32",
            "--encoder", "random", "--no-progress", "--episodes", "4", "--batch", "2"]
    args = parser.parse_args(base + ["--augment", "variants=2,hue_deg=20"])
    assert args.augment == AugmentConfig(variants=2, hue_deg=20)
    assert args.handler(args) == 0
    assert len((tmp_path / "run" / "metrics.csv").read_text().splitlines()) == 1 + 4
    config = json.loads((tmp_path / "run" / "config.json").read_text())
    assert config["augment"] == AugmentConfig(variants=2, hue_deg=20).to_dict()
    with pytest.raises(SystemExit):
        parser.parse_args(base + ["--augment", "hue_deg=500"])


def test_streamed_feature_table_equals_the_image_table_features(two_task_env):
    import torch

    from geonav.policy.config import NetConfig
    from geonav.policy.encoders import build_frozen_encoder

    frozen = build_frozen_encoder(NetConfig(encoder="random", obs_size_px=24))
    cfg = AugmentConfig(variants=2, seed=4)
    streamed = LatticeVecEnv(two_task_env, 1, augment=cfg).feature_table(frozen, chunk=16)
    venv = LatticeVecEnv(two_task_env, 1, augment=cfg)
    full = frozen.encode(torch.from_numpy(venv.image_table()))
    assert streamed.shape == (3 * venv.n_cells, frozen.out_dim)
    torch.testing.assert_close(streamed, full)
