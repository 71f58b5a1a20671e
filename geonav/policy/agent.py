"""From environment observations to network inputs and actions.

One code path for training rollouts, evaluation and deployment
(:class:`geonav.policy.inference.PolicyRunner`), so the greedy evaluation policy
and the flight policy act identically.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch

from geonav.policy.encoders import FrozenEncoder, cache_key
from geonav.policy.model import ActorCritic, State


@contextlib.contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Run a block with ``n`` torch intra-op threads (None: leave as is), then restore.

    Batch-1 policy steps are tiny: on a busy small CPU, 2 threads were 15-25x slower
    than 1 here (threads wait for each other), so acting defaults to one thread.
    """
    old = torch.get_num_threads()
    if n is None or n == old:
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def view_input(image: np.ndarray, frozen: FrozenEncoder | None,
               key: Any = None, target: np.ndarray | None = None) -> torch.Tensor:
    """One view as the network takes it: uint8 (N, N, 3) tensor, or (F,) frozen features.

    ``key`` (task, cell, altitude) selects the feature cache; None encodes directly.
    ``target``: the episode's target image (needed by a pairwise encoder, 'corr').
    """
    if frozen is None:
        return torch.from_numpy(np.ascontiguousarray(image))
    return frozen.features(image, key, target=target)


def obs_inputs(obs: dict[str, np.ndarray], info: dict[str, Any] | None,
               frozen: FrozenEncoder | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(current view, target view) inputs of an env observation; cached when ``info`` is given."""
    k_obs = cache_key(info) if (frozen is not None and info is not None) else None
    k_tgt = cache_key(info, target=True) if (frozen is not None and info is not None) else None
    tgt = obs["target"]
    return (view_input(obs["image"], frozen, k_obs, tgt),
            view_input(tgt, frozen, k_tgt, tgt))


def choose_action(logits: torch.Tensor, greedy: bool, rng: np.random.Generator | None) -> int:
    """argmax (greedy) or a draw from softmax(logits) with ``rng`` (logits: (A,))."""
    if greedy:
        return int(torch.argmax(logits).item())
    if rng is None:
        raise ValueError("sampled actions need an rng")
    cdf = np.cumsum(torch.softmax(logits, dim=-1).numpy(), dtype=np.float64)
    a = int(np.searchsorted(cdf, rng.random() * cdf[-1], side="right"))
    return min(a, cdf.shape[0] - 1)


class Agent:
    """A network plus its recurrent state, acting one step at a time (no gradients).

    Args:
        model: the actor-critic.
        frozen: the frozen encoder (None for the trainable CNN).
        greedy: default action mode (argmax); False samples.
        seed: seed of the sampling RNG.
    """

    def __init__(self, model: ActorCritic, frozen: FrozenEncoder | None = None, *,
                 greedy: bool = True, seed: int | None = 0) -> None:
        self.model = model
        self.frozen = frozen
        self.greedy = greedy
        self.rng = np.random.default_rng(seed)
        self.state: State = model.initial_state()
        self.target: torch.Tensor | None = None

    def reset(self) -> None:
        """Forget the LSTM state, previous action probabilities and target."""
        self.state = self.model.initial_state()
        self.target = None

    @torch.no_grad()
    def step_inputs(self, x: torch.Tensor, target: torch.Tensor, greedy: bool | None = None,
                    prev: torch.Tensor | None = None) -> int:
        """Advance one step from prepared inputs; returns the action.

        ``prev`` is the previous-altitude view for a network with the extra input slot
        (``NetConfig.prev_view_input``); None zero-fills that slot.
        """
        args: tuple[Any, ...] = (x.unsqueeze(0).unsqueeze(0), target.unsqueeze(0), self.state)
        if prev is not None:
            args = (*args, prev.unsqueeze(0).unsqueeze(0))
        logits, _, self.state = self.model(*args)
        return choose_action(logits[0, 0], self.greedy if greedy is None else greedy, self.rng)

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any] | None = None,
            greedy: bool | None = None) -> int:
        """One action for an env observation (``info`` enables the frozen feature cache)."""
        x, target = obs_inputs(obs, info, self.frozen)
        self.target = target
        return self.step_inputs(x, target, greedy)
