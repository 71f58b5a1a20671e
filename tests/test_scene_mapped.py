"""Scenes from packages: memory-mapped rasters, pickled as their path, shared render maps."""

import copy
import pickle

import numpy as np
import pytest

from geonav.camera import Camera, SliceRenderer
from geonav.scene import PACKAGE_CACHE, Scene, open_shared


@pytest.fixture(scope="module")
def package(tmp_path_factory, scene):
    return scene.save(tmp_path_factory.mktemp("mapped") / "T", compress="DEFLATE")


def test_rasters_are_read_only_maps_of_the_decoded_cache(package, scene):
    s = Scene.open(package)
    assert np.array_equal(s.rgb, scene.rgb) and np.array_equal(s.dsm, scene.dsm)
    assert isinstance(s.rgb.base, np.memmap) and not s.mask.flags.writeable
    names = sorted(p.name.split("-")[0] for p in (package / PACKAGE_CACHE).glob("*.npy"))
    assert names == ["dsm.dsm", "ortho.mask", "ortho.rgb"]
    with pytest.raises(ValueError, match="read-only"):
        s.rgb[0, 0] = 0
    again = Scene.open(package)  # maps the same files: no second decode
    assert again.rgb.base.filename == s.rgb.base.filename and again.is_mapped()


def test_pickle_copy_and_edits(package):
    s = Scene.open(package)
    back = pickle.loads(pickle.dumps(s))
    assert back is open_shared(package) and np.array_equal(back.rgb, s.rgb)
    shallow, deep = copy.copy(s), copy.deepcopy(s)
    assert shallow.is_mapped() and shallow.rgb is s.rgb
    assert not deep.is_mapped() and deep.rgb.flags.writeable and deep.rgb is not s.rgb
    s.mask = np.array(s.mask)  # an edited scene no longer pickles as its path
    assert not s.is_mapped() and len(pickle.dumps(s)) > s.mask.nbytes


def test_render_maps_shared_cached_and_invalidated(package, tmp_path):
    s = Scene.open(package)
    cam = Camera(32)
    a, b = SliceRenderer(s, cam), SliceRenderer(s, cam)
    va = a.view(0.0, 0.0, 45.0)
    assert np.shares_memory(va, b.view(0.0, 0.0, 45.0))
    assert np.array_equal(a.render(0.0, 0.0, 45.0), va) and a.render(0, 0, 45).flags.writeable
    assert len(list((package / PACKAGE_CACHE).glob("slice-32px-90deg-45m-fill0.*"))) == 1
    fresh = SliceRenderer(Scene.open(package), cam)  # another scene object: the cached file
    assert np.array_equal(fresh.view(0.0, 0.0, 45.0), va)
    assert a.coverage(0.0, 0.0, 45.0) == 1.0
    edited = Scene.open(package)
    edited.rgb = np.zeros_like(edited.rgb)  # replaced: new maps, not the cached ones
    assert not SliceRenderer(edited, cam).view(0.0, 0.0, 45.0).any()


def test_cache_off_and_read_only_package(package, tmp_path, monkeypatch, scene):
    monkeypatch.setenv("GEONAV_RASTER_CACHE", "0")
    s = Scene.open(package)
    assert not isinstance(s.rgb.base, np.memmap) and np.array_equal(s.rgb, scene.rgb)
    monkeypatch.delenv("GEONAV_RASTER_CACHE")
    monkeypatch.setenv("GEONAV_CACHE_DIR", str(tmp_path / "cache"))
    s = Scene.open(package)
    assert isinstance(s.rgb.base, np.memmap)
    assert len(list((tmp_path / "cache" / "scenes").glob("*/ortho.rgb-*.npy"))) == 1
