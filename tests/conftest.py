"""Shared fixtures: small scenes and tasks built in code."""

from __future__ import annotations

from pathlib import Path

import pytest

from geonav.testing import textured_scene, tiny_taskset

# The modules that take longest (pytest --durations, 2-core machine), run first: with
# scripts/test.sh's `-n 2 --dist loadfile` each module runs whole on one worker, and a long
# module left to the end would run alone while the other worker idles.
SLOW_MODULES = (
    "test_experiments_ray.py",
    "test_experiments.py",
    "test_corr_encoder.py",
    "test_experiments_faults.py",
    "test_experiments_packed.py",
    "test_batched_packed.py",
    "test_paper_parts.py",
    "test_batched_meta.py",
)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Slow modules first, each module's tests in their own order (a stable sort)."""
    rank = {name: i for i, name in enumerate(SLOW_MODULES)}
    items.sort(key=lambda it: rank.get(Path(str(it.path)).name, len(SLOW_MODULES)))


@pytest.fixture(scope="session")
def scene():
    """A 400 m textured scene at 0.5 m/px with 60 m towers and 12 m houses."""
    return textured_scene(400.0, 0.5, seed=0)


@pytest.fixture(scope="session")
def flat_scene():
    """A 400 m textured scene without a DSM."""
    s = textured_scene(400.0, 0.5, seed=1, towers=False)
    s.dsm = None
    return s


@pytest.fixture()
def tiny_tasks(scene):
    return tiny_taskset(scene)


@pytest.fixture
def float64_default(monkeypatch):
    """Every trainer built in the test in float64 (the default dtype), the frozen
    encoder's input included: the async reference and the batched engine compare to 1e-10."""
    import torch

    from geonav.policy import encoders

    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    to_float = encoders.images_to_float
    monkeypatch.setattr(encoders, "images_to_float",
                        lambda *a, **k: to_float(*a, **k).to(torch.float64))
    yield
    torch.set_default_dtype(old)
