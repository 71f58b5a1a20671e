"""PPO on the batched engine (``--algo ppo``): clipped surrogate, GAE, epochs of minibatches.

Per update (Schulman et al. 2017; CleanRL ``ppo.py``): act ``t_max`` steps in every slot,
keeping log pi(a_t) and V(s_t); masked GAE from those values
(:func:`~geonav.policy.losses.gae_returns`, lambda = ``loss.tau``); then ``epochs`` passes,
each over ``minibatches`` groups of whole slot sequences (the LSTM is recomputed from
each slot's stored start state with its episode starts, so the recurrent state is right
for every step of a minibatch), with the loss

    L = -mean min(rho A, clip(rho, 1 - eps, 1 + eps) A) + value_coef mean 1/2 (R - V)^2
        - beta mean H,    rho = pi(a | s) / pi_old(a | s),

and one Adam step per minibatch (gradient norm clipped to ``max_grad_norm``). The
network, checkpoints and metrics are the engine's (the same as A3C's).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch.nn import functional as F

from geonav.errors import ConfigError
from geonav.policy.batched.trainer import BatchedTrainer, RolloutBatch
from geonav.policy.config import A3CConfig, LossConfig
from geonav.policy.losses import clipped_surrogate


@dataclass(frozen=True)
class PPOConfig(A3CConfig):
    """PPO (CleanRL's defaults where the project has none); ``lr`` is Adam's."""

    t_max: int = 32
    """Steps per slot per rollout (the rollout holds t_max * batch steps)."""
    lr: float = 1e-3
    """Adam learning rate."""
    adam_eps: float = 1e-5
    """Adam epsilon (CleanRL)."""
    amsgrad: bool = False
    """AMSGrad variant (off, as CleanRL)."""
    max_grad_norm: float = 0.5
    """Gradient-norm clip per minibatch step."""
    epochs: int = 4
    """Passes over each rollout."""
    minibatches: int = 4
    """Minibatches per pass: groups of whole slot sequences (at most the batch)."""
    clip_coef: float = 0.2
    """epsilon of the clipped surrogate."""
    minibatch_steps: int = 0
    """0: ``minibatches`` minibatches per pass. N > 0: as many as hold about N env steps
    each (the rollout's t_max * batch steps / N, at least 1; SB3's ``batch_size``), so
    more slots take proportionally more gradient steps per rollout at the same minibatch
    size (issue 30's update-count scaling); overrides ``minibatches``."""
    seq_len: int = 0
    """Recurrent network: the length of the sequences PPO's minibatches are drawn from. 0:
    each slot's whole rollout (``t_max`` steps); L (a divisor of ``t_max``): the rollout
    cut into chunks of L steps, each recomputed from the recurrent state it was acted from,
    and minibatches drawn over all chunks of all slots (more, less correlated sequences
    per minibatch). The feed-forward network always draws single steps. Packed runs
    (``pack = true``) keep whole sequences either way."""
    normalize_advantages: bool = True
    """Standardise the advantages of each minibatch."""
    critic_warmup: int = 0
    """Rollouts at the start of training (of each call of ``train``) in which only the
    critic head learns, by its own Adam at ``lr``, from the value loss; every other weight
    stays as it is. Meant for fine-tuning a policy whose critic was trained on other tasks
    (a meta-policy's value loss starts 10-50x a converged one's, and its first updates
    undo the policy: docs/learning.md §14). 0: none."""
    loss: LossConfig = LossConfig(gamma=0.95, tau=0.95, bootstrap_on_truncation=True)
    """gamma, GAE lambda (tau), entropy weight (beta), value_coef, and the bootstrap at a
    time-limit truncation: V(s) of the last observation, as SB3 does, not 0 as at a
    terminal state (the default since issue 30: without it a critic that cannot see the
    step count is asked for both values at the same view; on view45-campus PPO needed
    1.6x the env steps with the corr encoder, and more than 2.7x with the feed-forward
    trainable CNN, docs/learning.md §14). ``{bootstrap_on_truncation = false}`` gives the
    earlier behaviour.

    gamma is 0.95, not the paper's 0.99 (the default since stop 43 of issue 30): at 0.99 a
    refused move into a wall, which leaves the view unchanged, costs the policy about 1 %
    of the state's value, so the greedy policy keeps some argmax pushing into walls for a
    whole episode; at 0.95 a lost step costs 5 %. On the four view-needing tasks it took
    the feed-forward trainable CNN to 0.58-0.82x SB3's env steps, from 0.67-1.27x
    (docs/learning.md §14, stop 43). ``{gamma = 0.99}`` gives the earlier behaviour."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.epochs < 1 or self.minibatches < 1:
            raise ConfigError(f"epochs and minibatches must be >= 1, got {self.epochs}, "
                              f"{self.minibatches}")
        if self.seq_len < 0 or (self.seq_len and self.t_max % self.seq_len):
            raise ConfigError(f"seq_len must be 0 or a divisor of t_max ({self.t_max}), got "
                              f"{self.seq_len}")
        if self.minibatch_steps < 0:
            raise ConfigError(f"minibatch_steps must be >= 0, got {self.minibatch_steps}")
        if self.critic_warmup < 0:
            raise ConfigError(f"critic_warmup must be >= 0, got {self.critic_warmup}")
        if not 0.0 < self.clip_coef < 1.0:
            raise ConfigError(f"clip_coef must lie in (0, 1), got {self.clip_coef}")


class BatchedPPOTrainer(BatchedTrainer):
    """PPO on the batched engine (see the module docstring); ``cfg`` is a :class:`PPOConfig`."""

    algorithm = "ppo"
    config_key = "ppo"
    cfg: PPOConfig

    def __init__(self, env_factory: Any, net_cfg: Any = None, cfg: PPOConfig | None = None,
                 **kwargs: Any) -> None:
        super().__init__(env_factory, net_cfg, cfg if cfg is not None else PPOConfig(),
                         **kwargs)

    def ppo_loss(self, ro: RolloutBatch, slots: torch.Tensor, returns: torch.Tensor,
                 advantages: torch.Tensor, sizes: list[int] | None = None
                 ) -> list[dict[str, torch.Tensor]]:
        """The clipped-surrogate loss of a minibatch of slot sequences, one per run: the
        columns are ``sizes`` groups in run order (packed runs; None: one run)."""
        cfg = self.cfg
        logits, values = self.recompute(ro, slots)
        assert ro.logprobs is not None
        logp_all = F.log_softmax(logits, -1)
        logp = logp_all.gather(-1, ro.actions[:, slots].unsqueeze(-1)).squeeze(-1)
        out = []
        for cols in torch.arange(len(slots)).split(sizes or [len(slots)]):
            adv = advantages[:, slots[cols]]
            if cfg.normalize_advantages and adv.numel() > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg = clipped_surrogate(logp[:, cols], ro.logprobs[:, slots[cols]], adv,
                                   cfg.clip_coef).mean()
            lp = logp_all[:, cols]
            entropy = -(lp.exp() * lp).sum(-1).mean()
            value = (0.5 * (returns[:, slots[cols]] - values[:, cols]).pow(2)).mean()
            total = pg - cfg.loss.beta * entropy + cfg.loss.value_coef * value
            out.append({"total": total, "policy": pg, "value": value, "entropy": entropy})
        return out

    def minibatch_count(self, columns: int, steps_per_column: int) -> int:
        """Minibatches per pass over ``columns`` sequences of ``steps_per_column`` steps
        (``minibatch_steps``, else ``minibatches``)."""
        cfg = self.cfg
        if not cfg.minibatch_steps:
            return cfg.minibatches
        return max(1, round(columns * steps_per_column / cfg.minibatch_steps))

    def critic_update(self, ro: RolloutBatch, returns: torch.Tensor) -> dict[str, Any]:
        """A warm-up update (``critic_warmup``): ``epochs`` Adam steps of the critic head
        on the rollout's value loss, the policy and every other weight unchanged."""
        if len(self.run_slices()) > 1:
            raise ConfigError("critic_warmup is not supported for packed runs (pack = true); "
                              "run the stage's seeds unit by unit")
        value = torch.zeros(())
        for _ in range(self.cfg.epochs):
            _, values = self.recompute(ro)
            value = _critic_step(self, values, returns)
        return {"policy_loss": 0.0, "value_loss": float(value), "entropy": 0.0,
                "critic_warmup": True}

    warmup_done: int = 0
    """Critic warm-up rollouts done in this call of ``train`` (``critic_warmup``)."""

    def update(self) -> tuple[list[dict[str, Any]], Any]:
        cfg, b = self.cfg, self.run_batch
        single = len(self.run_slices()) == 1
        chunks = self.net_cfg.recurrent and single and 0 < cfg.seq_len < cfg.t_max
        ro, finals = self.collect(cfg.t_max, keep_policy=True, keep_states=chunks)
        assert ro.values is not None
        returns, advantages = self.advantages(ro, ro.values)
        if self.warmup_done < cfg.critic_warmup:
            self.warmup_done += 1
            return finals, self.critic_update(ro, returns)
        if not self.net_cfg.recurrent and single:
            # a feed-forward policy needs no sequences: minibatches of single steps
            ro, returns, advantages = flat_steps(ro, returns, advantages)
            b = ro.view_idx.shape[1]
        elif chunks:
            ro, returns, advantages = chunk_steps(ro, returns, advantages, cfg.seq_len)
            b = ro.view_idx.shape[1]
        n_mb = min(self.minibatch_count(b, ro.view_idx.shape[0]), b)
        outs: list[dict[str, torch.Tensor]] = []
        for _ in range(cfg.epochs):  # each run's slots in its own order, from its own stream
            perms = [torch.from_numpy(rng.permutation(b)).to(self.device) + i * b
                     for i, rng in enumerate(self.run_rngs())]
            for j in range(n_mb):
                parts = [p.chunk(n_mb)[j] for p in perms]
                outs = self.ppo_loss(ro, torch.cat(parts), returns, advantages,
                                     [len(p) for p in parts])
                self.step_optimizer(torch.stack([o["total"] for o in outs]).sum())
        stats = [{"policy_loss": float(o["policy"].detach()),
                  "value_loss": float(o["value"].detach()),
                  "entropy": float(o["entropy"].detach())} for o in outs]
        return finals, stats[0] if len(stats) == 1 else stats


def _critic_params(trainer: BatchedPPOTrainer) -> list[torch.Tensor]:
    names = [n for n, _ in trainer.model.named_parameters()]
    return [p for n, p in zip(names, trainer.params_list, strict=True)
            if n.startswith("critic.")]


def _critic_step(trainer: BatchedPPOTrainer, values: torch.Tensor, returns: torch.Tensor
                 ) -> torch.Tensor:
    """One Adam step of the critic head alone on 1/2 (R - V)^2; returns the loss."""
    if getattr(trainer, "_critic_opt", None) is None:
        trainer._critic_opt = torch.optim.Adam(  # type: ignore[attr-defined]
            _critic_params(trainer), lr=trainer.cfg.lr, eps=trainer.cfg.adam_eps)
    opt = trainer._critic_opt  # type: ignore[attr-defined]
    loss = (0.5 * (returns - values).pow(2)).mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    opt.step()
    return loss.detach()


def flat_steps(ro: RolloutBatch, returns: torch.Tensor, advantages: torch.Tensor
               ) -> tuple[RolloutBatch, torch.Tensor, torch.Tensor]:
    """A rollout of T steps of B slots as one step of T x B slots (column s * T + t), each
    starting an episode from a zero state: for a feed-forward network (NetConfig.recurrent
    False) the same logits and values, and PPO's minibatches become single steps drawn
    across slots and times, as in SB3 (not whole, correlated slot sequences)."""
    from dataclasses import replace

    zero = tuple(torch.zeros(ro.view_idx.shape[0], *x.shape, dtype=x.dtype, device=x.device)
                 for x in ro.start_state)  # (T, B, ...): no step carries a state
    return chunk_steps(replace(ro, step_states=zero, starts=torch.ones_like(ro.starts)),
                       returns, advantages, 1)


def chunk_steps(ro: RolloutBatch, returns: torch.Tensor, advantages: torch.Tensor,
                seq_len: int) -> tuple[RolloutBatch, torch.Tensor, torch.Tensor]:
    """A rollout of T steps of B slots as T / L chunks of L = ``seq_len`` steps per slot:
    L steps of B * T / L columns (column s * T / L + j is slot s's chunk j), each starting
    from the recurrent state chunk j's first step was acted from (``ro.step_states``), so
    the recompute gives the acting logits and values; PPO then draws its minibatches over
    all chunks (the recurrent counterpart of :func:`flat_steps`)."""
    from dataclasses import replace

    assert ro.step_states is not None and ro.logprobs is not None
    T, B = ro.view_idx.shape
    n = T // seq_len

    def chunk(x: torch.Tensor) -> torch.Tensor:  # (T, B) -> (L, B * n)
        return x.reshape(n, seq_len, B).permute(1, 2, 0).reshape(seq_len, B * n)

    first = tuple(x[::seq_len].transpose(0, 1).reshape(B * n, *x.shape[2:])
                  for x in ro.step_states)  # (n, B, ...) -> (B * n, ...)
    out = replace(ro, start_state=first, view_idx=chunk(ro.view_idx),  # type: ignore[arg-type]
                  target_idx=chunk(ro.target_idx), actions=chunk(ro.actions),
                  starts=chunk(ro.starts), logprobs=chunk(ro.logprobs), step_states=None)
    return out, chunk(returns), chunk(advantages)


__all__ = ["PPOConfig", "BatchedPPOTrainer", "chunk_steps", "flat_steps"]
