"""GeoNavEnv in the Gymnasium ecosystem: registration, vector envs, pickling, shared maps."""

import pickle
import subprocess
import sys

import gymnasium
import numpy as np
import pytest

from geonav.env import ENV_ID, GeoNavEnv
from geonav.scene import Scene
from geonav.testing import tiny_taskset


@pytest.fixture(scope="module")
def package(tmp_path_factory, scene):
    """The session scene as a package on disk (DEFLATE: lossless)."""
    return scene.save(tmp_path_factory.mktemp("pkg") / "T", compress="DEFLATE")


def test_import_geonav_registers_without_heavy_imports():
    code = ("import sys, geonav, gymnasium; "
            "assert 'geonav/GeoNav-v0' in gymnasium.registry; "
            "print(sorted(m for m in ('torch', 'rasterio', 'cv2', 'geonav.env') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "[]"
    assert gymnasium.registry[ENV_ID].entry_point == "geonav.env:GeoNavEnv"


def test_is_success_beside_success(scene):
    ts = tiny_taskset(scene, cells=3, target=(2, 2))
    env = GeoNavEnv(scene, ts)
    _, info = env.reset(seed=0, options={"start_cell": (1, 2)})
    assert info["is_success"] is False and info["success"] is False
    _, r, te, _, info = env.step(1)
    assert te and r == 5.0 and info["is_success"] is True and info["success"] is True


def test_pickle_is_paths_and_parameters(package, scene):
    opened = Scene.open(package)
    assert opened.is_mapped() and not opened.rgb.flags.writeable
    assert len(pickle.dumps(opened)) < 1000  # the path, not the 800x800 rasters
    ts = tiny_taskset(opened)
    env = GeoNavEnv(opened, ts, render_mode="rgb_array")
    env.reset(seed=5)
    env.step(0)
    blob = pickle.dumps(env)
    assert len(blob) < 20_000, len(blob)
    mem_env = GeoNavEnv(scene, tiny_taskset(scene))
    mem_env.reset(seed=0)  # builds the 75 m map on the scene
    in_memory = len(pickle.dumps(mem_env))
    arrays = scene.rgb.nbytes + scene.mask.nbytes + scene.dsm.nbytes
    assert arrays < in_memory < arrays + 50_000  # an in-memory scene: its arrays, no caches
    twin = pickle.loads(blob)
    # the round trip keeps the episode and the generator: both continue identically
    for a in (1, 1, 0, 3, 2, 0, 0):
        o1, r1, te1, tr1, i1 = env.step(a)
        o2, r2, te2, tr2, i2 = twin.step(a)
        assert (r1, te1, tr1, i1) == (r2, te2, tr2, i2)
        assert np.array_equal(o1["image"], o2["image"])
        assert np.array_equal(o1["target"], o2["target"])
    assert env.reset()[1]["cell"] == twin.reset()[1]["cell"]
    assert twin.render().shape == env.render().shape


def test_envs_of_a_process_share_one_map(package):
    ts = tiny_taskset(Scene.open(package))
    a, b = GeoNavEnv(package, ts), GeoNavEnv(str(package), ts)
    assert a.scene is b.scene  # one scene per package and process
    c = pickle.loads(pickle.dumps(a))
    assert c.scene is a.scene
    va, vb, vc = (e._view(0, (1, 2)) for e in (a, b, c))
    assert np.shares_memory(va, vb) and np.shares_memory(va, vc)
    assert not va.flags.writeable
    # the map is a memory-mapped file of the package's raster cache, reused on reopen
    cached = sorted(p.name for p in (package / ".geonav-cache").glob("slice-*.npy"))
    assert len(cached) == 1 and "84px-90deg-75m" in cached[0]
    obs, _ = a.reset(seed=0)
    assert obs["image"].flags.writeable  # what the agent gets is its own copy


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_make_vec(package, mode):
    ts = tiny_taskset(Scene.open(package))
    # async in fresh interpreters (forkserver): the env factory and its scene are pickled
    kwargs = {"context": "forkserver"} if mode == "async" else {}
    vec = gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode=mode, scene=package,
                             tasks=ts, vector_kwargs=kwargs)
    try:
        obs, infos = vec.reset(seed=[3, 4])
        assert obs["image"].shape == (2, 84, 84, 3) and obs["image"].dtype == np.uint8
        ref = GeoNavEnv(package, ts)
        ref_obs, ref_info = ref.reset(seed=3)
        assert np.array_equal(obs["image"][0], ref_obs["image"])
        assert tuple(infos["cell"][0]) == ref_info["cell"]
        rng = np.random.default_rng(0)
        succeeded = 0
        for _ in range(80):
            actions = rng.integers(0, 4, 2)
            obs, rewards, te, tr, infos = vec.step(actions)
            assert set(infos["is_success"][te]) <= {True}
            succeeded += int(te.sum())
        assert succeeded > 0 and infos["is_success"].dtype == bool
    finally:
        vec.close()
