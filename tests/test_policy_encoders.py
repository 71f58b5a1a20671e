"""Encoders: the feature cache, the random frozen CNN and the optional ResNet18."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geonav.errors import MissingExtra
from geonav.policy.config import NetConfig
from geonav.policy.encoders import build_frozen_encoder, cache_key, feature_dim


def _torchvision_available() -> bool:
    try:
        import torchvision  # noqa: F401
    except Exception:
        return False
    return True


def test_random_encoder_is_reproducible_and_frozen():
    a = build_frozen_encoder(NetConfig(encoder="random", obs_size_px=32))
    b = build_frozen_encoder(NetConfig(encoder="random", obs_size_px=32))
    img = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    fa, fb = a.encode(img), b.encode(img)
    assert fa.shape == (1, feature_dim(NetConfig(obs_size_px=32))) and torch.equal(fa, fb)
    assert not any(p.requires_grad for p in a.net.parameters())


def test_feature_cache_encodes_each_view_once():
    enc = build_frozen_encoder(NetConfig(encoder="random", obs_size_px=32))
    info = {"task_index": 0, "cell": (1, 2), "target_cell": (3, 3), "alt_m": 75.0}
    img = np.full((32, 32, 3), 7, np.uint8)
    f1 = enc.features(img, cache_key(info))
    f2 = enc.features(np.zeros_like(img), cache_key(info))  # same key: cached value
    assert torch.equal(f1, f2) and enc.misses == 1 and enc.hits == 1
    enc.features(img, cache_key({**info, "alt_m": 45.0}))
    enc.features(img, cache_key(info, target=True))
    assert len(enc) == 3


@pytest.mark.skipif(_torchvision_available(), reason="torchvision is installed here")
def test_resnet_without_torchvision_names_the_extra():
    with pytest.raises(MissingExtra, match=r"geonav\[resnet\]"):
        build_frozen_encoder(NetConfig(encoder="resnet18"))


@pytest.mark.skipif(not _torchvision_available(),
                    reason="torchvision (geonav[resnet]) does not import beside this torch build")
def test_resnet_from_local_weights(tmp_path):
    from torchvision.models import resnet18

    path = tmp_path / "r18.pt"
    torch.save(resnet18(weights=None).state_dict(), path)
    enc = build_frozen_encoder(NetConfig(encoder="resnet18", encoder_weights=str(path)))
    assert enc.encode(np.zeros((84, 84, 3), np.uint8)).shape == (1, 512)


def test_one_encoder_serves_envs_on_different_scenes():
    """The cache key names the scene and the task, so a second env's views are not the
    first env's features (same task index, cell and altitude, different imagery)."""
    from geonav.env import GeoNavEnv
    from geonav.testing import textured_scene, tiny_taskset

    enc = build_frozen_encoder(NetConfig(encoder="random"))
    feats, infos = [], []
    for seed in (0, 1):
        scene = textured_scene(300.0, seed=seed, towers=False)
        obs, info = GeoNavEnv(scene, tiny_taskset(scene)).reset(
            seed=0, options={"start_cell": (0, 0)})
        infos.append(info)
        feats.append(enc.features(obs["image"], cache_key(info)))
    assert infos[0]["task_index"] == infos[1]["task_index"]
    assert infos[0]["task_key"] != infos[1]["task_key"]
    assert enc.misses == 2 and not torch.equal(feats[0], feats[1])
    # the same scene and task built again gives the same key (a cache hit)
    scene = textured_scene(300.0, seed=0, towers=False)
    _, info = GeoNavEnv(scene, tiny_taskset(scene)).reset(seed=0, options={"start_cell": (0, 0)})
    assert info["task_key"] == infos[0]["task_key"]


def test_nature_cnn_sizes_and_refusals():
    """NetConfig.cnn='nature': three convolutions (32/64/64) whose feature width the
    network's embeddings are built for; too-small views and unknown kinds are refused."""
    import pytest
    import torch

    from geonav.errors import ConfigError
    from geonav.policy.config import NetConfig
    from geonav.policy.encoders import feature_dim
    from geonav.policy.model import ActorCritic

    for px, width in ((64, 1024), (84, 3136)):
        cfg = NetConfig(obs_size_px=px, cnn="nature")
        model = ActorCritic(cfg)
        assert feature_dim(cfg) == width == model.obs_embed.in_features
        assert model.encoder.conv3 is not None
        feats = model.features(torch.zeros(2, px, px, 3, dtype=torch.uint8))
        assert feats.shape == (2, width)
    assert ActorCritic(NetConfig(obs_size_px=64)).encoder.conv3 is None  # default: small
    with pytest.raises(ConfigError, match="36 px"):
        NetConfig(obs_size_px=32, cnn="nature")
    with pytest.raises(ConfigError, match="cnn must be one of"):
        NetConfig(cnn="resnet")
