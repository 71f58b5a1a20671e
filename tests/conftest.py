"""Shared fixtures: small scenes and tasks built in code."""

from __future__ import annotations

import pytest

from geonav.testing import textured_scene, tiny_taskset


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
