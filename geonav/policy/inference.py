"""Run a trained policy outside the training environment (the MAVLink flight loop).

    runner = PolicyRunner.from_checkpoint("run/checkpoints/final.pt")
    runner.reset()
    while flying:
        action = runner.act(image, target)   # (N, N, 3) uint8 each -> 0..3

The runner keeps the LSTM state and previous action probabilities across
calls; :meth:`reset` starts a new episode. Actions are greedy by default and
come from the same :class:`geonav.policy.agent.Agent` code path as
:func:`geonav.policy.evaluation.evaluate`, so they match greedy evaluation.

A policy with the curriculum's extra input slot (``NetConfig.prev_view_input``,
ALGORITHMS.md (e) option B) takes the view at the same place at the previous stage's
altitude. Flight has no such view: unless :meth:`PolicyRunner.act` is given
``prev_image``, the slot is **zero-filled**, as in stage 0 and in evaluation, which
differs from what later curriculum stages were trained with.
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
    def prev_view_input(self) -> bool:
        """True when the policy has the extra previous-altitude input slot (zero-filled
        unless ``act`` gets ``prev_image``)."""
        return bool(self.agent.model.cfg.prev_view_input)

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

    def act(self, image: np.ndarray, target: np.ndarray, *, greedy: bool | None = None,
            prev_image: np.ndarray | None = None) -> int:
        """The next action (0 forward/north, 1 right/east, 2 left/west, 3 backward/south).

        ``prev_image``: the view at the same place at the previous curriculum altitude, for
        a policy with the extra input slot (:attr:`prev_view_input`); None (the flight
        loop) zero-fills the slot. Refused for a policy without the slot.
        """
        image = self._check("current", image)
        target = self._check("target", target)
        prev = None
        if prev_image is not None:
            if not self.prev_view_input:
                raise CheckpointError("this policy has no previous-view input slot "
                                      "(prev_view_input=False); do not pass prev_image")
            prev = self._check("previous-altitude", prev_image)
        with torch_threads(self.threads):
            return self._act(image, target, greedy, prev)

    def check_outputs(self, image: np.ndarray, target: np.ndarray) -> None:
        """Run the network once on a view and a target view (its state untouched) and refuse
        non-finite action logits or value: such a policy cannot choose an action.

        Raises:
            CheckpointError: naming the outputs and what to do.
        """
        image = self._check("current", image)
        target = self._check("target", target)
        model = self.agent.model
        with torch_threads(self.threads), torch.no_grad():
            x = view_input(image, self.agent.frozen, target=target)
            t = view_input(target, self.agent.frozen, target=target)
            logits, value, _ = model(x.unsqueeze(0).unsqueeze(0), t.unsqueeze(0),
                                     model.initial_state())
        if not (bool(torch.isfinite(logits).all()) and bool(torch.isfinite(value).all())):
            raise CheckpointError(
                f"the policy's outputs are not finite on this scene's views (action logits "
                f"{[round(float(v), 3) for v in logits.flatten()[:4]]}, value "
                f"{float(value.flatten()[0]):.3g}): it cannot choose an action; use another "
                "checkpoint of the run")

    def _act(self, image: np.ndarray, target: np.ndarray, greedy: bool | None,
             prev_image: np.ndarray | None = None) -> int:
        if self._target is None or self._target_image is None or \
                not np.array_equal(target, self._target_image):
            self._target_image = target.copy()
            self._target = view_input(target, self.agent.frozen, target=target)
        x = view_input(image, self.agent.frozen, target=target)
        prev = None if prev_image is None else view_input(prev_image, self.agent.frozen)
        return self.agent.step_inputs(x, self._target, greedy, prev)
