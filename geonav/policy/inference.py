"""Run a trained policy outside the training environment (the MAVLink flight loop).

    runner = PolicyRunner.from_checkpoint("run/checkpoints/final.pt")
    runner.reset()
    while flying:
        action = runner.act(image, target)   # (N, N, 3) uint8 each -> 0..3

The runner keeps the LSTM state and previous action probabilities across
calls; :meth:`reset` starts a new episode. Actions are greedy by default and
come from the same :class:`geonav.policy.agent.Agent` code path as
:func:`geonav.policy.evaluation.evaluate`, so they match greedy evaluation.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch

from geonav.errors import CheckpointError
from geonav.policy.agent import Agent, torch_threads, view_input
from geonav.policy.checkpoint import load_checkpoint


class PolicyRunner:
    """A checkpointed policy acting on raw images.

    Attributes:
        meta: the checkpoint's meta (``obs_size_px``, ``alt_m``, ``step_m``, ``fov_deg``,
            ``action_meanings``, ``algorithm``, ``episodes``, ...).
    """

    def __init__(self, agent: Agent, meta: dict[str, Any], threads: int | None = 1) -> None:
        self.agent = agent
        self.threads = threads
        self.meta = meta
        self.obs_size_px = int(meta["obs_size_px"])
        self._target_image: np.ndarray | None = None
        self._target: torch.Tensor | None = None

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike[str], *, greedy: bool = True,
                        seed: int = 0, threads: int | None = 1) -> PolicyRunner:
        """Load a checkpoint (``weights_only``); raises :class:`CheckpointError` if unusable.

        Args:
            path: the checkpoint.
            greedy: argmax actions (default) or samples.
            seed: seed of sampled actions.
            threads: torch threads used inside :meth:`act` (restored after each call).
        """
        ckpt = load_checkpoint(path)
        model = ckpt.build_model()
        return cls(Agent(model, ckpt.build_encoder(), greedy=greedy, seed=seed), ckpt.meta,
                   threads)

    @property
    def action_meanings(self) -> list[str]:
        return list(self.meta.get("action_meanings", []))

    def reset(self) -> None:
        """Start a new episode: zero LSTM state and previous action probabilities."""
        self.agent.reset()
        self._target_image = None
        self._target = None

    def _check(self, name: str, image: np.ndarray) -> np.ndarray:
        image = np.asarray(image)
        n = self.obs_size_px
        if image.shape != (n, n, 3) or image.dtype != np.uint8:
            raise CheckpointError(f"the policy takes {name} images of shape ({n}, {n}, 3) uint8, "
                                  f"got {image.shape} {image.dtype}; render at obs_size_px={n}")
        return image

    def act(self, image: np.ndarray, target: np.ndarray, *, greedy: bool | None = None) -> int:
        """The next action (0 forward/north, 1 right/east, 2 left/west, 3 backward/south)."""
        image = self._check("current", image)
        target = self._check("target", target)
        with torch_threads(self.threads):
            return self._act(image, target, greedy)

    def _act(self, image: np.ndarray, target: np.ndarray, greedy: bool | None) -> int:
        if self._target is None or self._target_image is None or \
                not np.array_equal(target, self._target_image):
            self._target_image = target.copy()
            self._target = view_input(target, self.agent.frozen)
        x = view_input(image, self.agent.frozen)
        return self.agent.step_inputs(x, self._target, greedy)
