"""The A3C worker (ALGORITHMS.md (a)): one process's episodes against the shared model, its
rollouts and their loss, and the worker process's entry point. :class:`A3CTrainer`
(:mod:`geonav.policy.a3c`) starts and feeds them; ISAR's and SAVN's workers extend
:class:`A3CWorker`."""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import nn

from geonav.policy.agent import choose_action, obs_inputs
from geonav.policy.config import A3CConfig, NetConfig
from geonav.policy.encoders import FrozenEncoder, build_frozen_encoder
from geonav.policy.evaluation import spl
from geonav.policy.losses import actor_critic_loss
from geonav.policy.model import ActorCritic, State
from geonav.policy.optim import SharedAdam, warm_up_lr

EnvFactory = Callable[[], Any]
"""A picklable zero-argument callable that builds the training env."""


@dataclass
class Rollout:
    """Up to ``t_max`` steps of one episode, stored for the batched loss recompute."""

    start_state: State
    target: torch.Tensor
    views: list[torch.Tensor] = field(default_factory=list)
    actions: list[int] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.actions)


def _plain_state(state: State) -> State:
    """A graph-free copy of a recurrent state that autograd may save (not an inference tensor)."""
    return (state[0].detach().clone(), state[1].detach().clone(), state[2].detach().clone())


def rollout_loss(model: nn.Module, rollout: Rollout, bootstrap: float, cfg: A3CConfig,
                 params: dict[str, torch.Tensor] | None = None) -> Any:
    """L_AC of a stored rollout, recomputed in one forward call from its start state.

    Args:
        model: the actor-critic.
        rollout: the stored steps.
        bootstrap: B (0 when the rollout ended the episode).
        cfg: trainer config (its ``loss``).
        params: optional name -> tensor dict for ``functional_call`` (SAVN/ISAR).
    """
    views = torch.stack(rollout.views).unsqueeze(1)            # (T, 1, ...)
    args = (views, rollout.target.unsqueeze(0), rollout.start_state)
    if params is None:
        logits, values, _ = model(*args)
    else:
        logits, values, _ = torch.func.functional_call(model, params, args, strict=True)
    return actor_critic_loss(logits[:, 0], values[:, 0], rollout.actions, rollout.rewards,
                             bootstrap, cfg.loss)


class A3CWorker:
    """One A3C worker: a local network, an env, and the shared model and optimiser.

    With ``shared_model=None`` the local network *is* the shared one (single process).
    """

    def __init__(self, rank: int, model: ActorCritic, optimizer: torch.optim.Optimizer,
                 env: Any, cfg: A3CConfig, frozen: FrozenEncoder | None, seed: int,
                 shared_model: ActorCritic | None = None,
                 rng_state: dict[str, Any] | None = None) -> None:
        self.rank = rank
        self.model = model
        self.shared = shared_model
        self.optimizer = optimizer
        self.env = env
        self.cfg = cfg
        self.frozen = frozen
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self._env_seeded = False
        self.env_steps = 0
        self.reset_options: dict[str, Any] | None = None
        """Options of the next ``env.reset`` (meta-training picks the task with them)."""
        self.on_gradients: Callable[[list[torch.Tensor]], None] | None = None
        """Called with the unclipped gradients of every update before the optimiser steps
        (meta-training sums them into the task gradient)."""
        self._params: list[torch.Tensor] = list(model.parameters())
        self._shared_params: list[torch.Tensor] | None = list(shared_model.parameters()) \
            if shared_model is not None else None
        if rng_state is not None:
            self.set_rng_state(rng_state)

    @classmethod
    def create(cls, rank: int, shared_model: ActorCritic, optimizer: torch.optim.Optimizer,
               env: Any, net_cfg: NetConfig, cfg: A3CConfig, frozen: FrozenEncoder | None,
               seed: int, extra: dict[str, Any] | None = None) -> A3CWorker:
        """The worker of a worker process: a local copy of the shared network.

        ``extra`` carries what subclasses share beyond the policy (see
        :meth:`A3CTrainer.worker_extra`).
        """
        local = ActorCritic(net_cfg)
        local.load_state_dict(shared_model.state_dict())
        return cls(rank, local, optimizer, env, cfg, frozen, seed, shared_model=shared_model)

    def reset_env(self) -> tuple[Any, dict[str, Any]]:
        """``env.reset``, seeded on the first call, with :attr:`reset_options`."""
        if not self._env_seeded:
            self._env_seeded = True
            return self.env.reset(seed=self.seed, options=self.reset_options)
        return self.env.reset(options=self.reset_options)

    # -- RNG state (exact resume in single-process mode) ----------------------------------
    def rng_state(self) -> dict[str, Any]:
        return {"torch": torch.get_rng_state(), "numpy": self.rng.bit_generator.state,
                "env": self.env.unwrapped.np_random.bit_generator.state,
                "env_seeded": self._env_seeded}

    def set_rng_state(self, st: dict[str, Any]) -> None:
        torch.set_rng_state(st["torch"])
        self.rng.bit_generator.state = st["numpy"]
        self.env.unwrapped.np_random.bit_generator.state = st["env"]
        self._env_seeded = bool(st["env_seeded"])

    # -- the algorithm --------------------------------------------------------------------
    def sync(self) -> None:
        """Step 1: local parameters <- shared parameters."""
        if self._shared_params is not None:
            with torch.no_grad():
                torch._foreach_copy_(self._params, self._shared_params)

    def update(self, rollout: Rollout, bootstrap: float) -> Any:
        """Steps 3-4: batched recompute, L_AC, backward, clip, shared Adam step."""
        for p in self._params:
            p.grad = None
        loss = rollout_loss(self.model, rollout, bootstrap, self.cfg)
        loss.total.backward()
        self.apply_gradients()
        return loss

    def apply_gradients(self) -> None:
        """Show the local ``.grad`` to :attr:`on_gradients` (unclipped), clip it to
        ``max_grad_norm``, hand it to the shared parameters and step the shared optimiser."""
        if self.on_gradients is not None:
            self.on_gradients([p.grad for p in self._params])  # type: ignore[misc]
        if self.cfg.max_grad_norm:
            nn.utils.clip_grad_norm_(self._params, self.cfg.max_grad_norm)
        if self._shared_params is not None:
            for p, sp in zip(self._params, self._shared_params, strict=True):
                sp.grad = p.grad
        warm_up_lr(self.optimizer, self.cfg.lr, self.cfg.lr_warmup)
        self.optimizer.step()

    def run_episode(self, episode: int) -> dict[str, Any]:
        """Play one training episode, updating every ``t_max`` steps; returns its record."""
        t0 = time.perf_counter()
        cfg = self.cfg
        obs, info = self.reset_env()
        shortest = int(info["shortest_path"])
        state = self.model.initial_state()
        ep_return, length, collisions = 0.0, 0, 0
        pl = vl = ent = 0.0
        n_updates = 0
        terminated = truncated = False
        view, target = obs_inputs(obs, info, self.frozen)
        while not (terminated or truncated):
            self.sync()
            # Clone: the state may come from inference mode, and the recompute needs a
            # plain tensor as its (constant) start.
            ro = Rollout(_plain_state(state), target)
            with torch.inference_mode():  # ~25% cheaper than no_grad for batch-1 steps
                target_feat = self.model.features(target[None])  # once per rollout
                for _ in range(cfg.t_max):
                    logits, _, state = self.model(view[None, None], target_feat, state)
                    a = choose_action(logits[0, 0], False, self.rng)
                    obs, r, terminated, truncated, info = self.env.step(a)
                    ro.views.append(view)
                    ro.actions.append(a)
                    ro.rewards.append(float(r))
                    ep_return += float(r)
                    length += 1
                    collisions += int(bool(info["collided"]))
                    view, _ = obs_inputs(obs, info, self.frozen)
                    if terminated or truncated:
                        break
                if terminated or (truncated and not cfg.loss.bootstrap_on_truncation):
                    bootstrap = 0.0
                else:  # V(s_next): an extra forward that does not advance the state
                    _, v_next, _ = self.model(view[None, None], target_feat, state)
                    bootstrap = float(v_next[0, 0])
            loss = self.update(ro, bootstrap)
            pl += loss.policy.item()
            vl += loss.value.item()
            ent += loss.entropy.item() / len(ro)
            n_updates += 1
        self.env_steps += length
        success = bool(info["success"])
        return {"episode": episode, "worker": self.rank, "task": info["task"],
                "task_index": int(info["task_index"]), "return": ep_return, "length": length,
                "success": success, "spl": spl(success, shortest, length),
                "collisions": collisions, "shortest_path": shortest,
                "policy_loss": pl / n_updates, "value_loss": vl / n_updates,
                "entropy": ent / n_updates, "env_steps": length,
                "wall_s": time.perf_counter() - t0}


def _worker_process(rank: int, shared_model: ActorCritic, optimizer: SharedAdam,
                    env_factory: EnvFactory, net_cfg: NetConfig, cfg: A3CConfig, seed: int,
                    counter: Any, lock: Any, results: Any, stop: Any, ready: Any,
                    worker_cls: type[A3CWorker] = A3CWorker,
                    extra: dict[str, Any] | None = None) -> None:
    """Process target: claim episode numbers from the global counter until the budget is spent."""
    try:
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(seed)
        env = env_factory()
        worker = worker_cls.create(rank, shared_model, optimizer, env, net_cfg, cfg,
                                   build_frozen_encoder(net_cfg), seed, extra)
        ready.wait(timeout=300)  # start together, so every worker takes part from episode 1
        while not stop.is_set():
            with lock:
                if counter.value >= cfg.episodes:
                    break
                counter.value += 1
                episode = counter.value
            results.put(("episode", rank, worker.run_episode(episode)))
        results.put(("done", rank, None))
    except BaseException:  # report everything, including KeyboardInterrupt, to the main process
        results.put(("error", rank, traceback.format_exc()))
