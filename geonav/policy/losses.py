"""The segment actor-critic loss L_AC (ALGORITHMS.md 4.0), written once.

For a segment S of T steps with log-probabilities, entropies and values from
forward passes that kept the graph (per step, or recomputed in one batch):

* bootstrap B = 0 if S ended the episode, else V(s_next), detached;
* backward recursion R <- r_t + gamma R; value loss sum_t 1/2 (R_t - V_t)^2;
* delta_t = r_t + gamma V_{t+1} - V_t with detached values (V_T = B);
  gae <- gamma tau gae + delta_t; policy loss sum_t -log pi(a_t) gae_t - beta H_t;
* L = policy + value_coef * value  (value_coef = 0.5).

This is rl_a3c_pytorch / allenai/savn ``a3c_loss`` vectorised: returns and
advantages do not depend on the parameters, so they are computed once from
detached values and the loss is a sum of per-step terms, which is the same
number and the same gradient as the step-by-step recursion.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch.nn import functional as F

from geonav.policy.config import LossConfig


@dataclass
class LossTerms:
    """The pieces of L_AC (scalar tensors; ``total`` carries the graph)."""

    total: torch.Tensor
    policy: torch.Tensor
    value: torch.Tensor
    entropy: torch.Tensor
    """Summed entropy over the segment (already included in ``policy``, times -beta)."""


def returns_and_advantages(rewards: Sequence[float] | torch.Tensor, values: torch.Tensor,
                           bootstrap: float, gamma: float, tau: float
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """Discounted returns R_t and GAE advantages for one segment.

    Args:
        rewards: r_0..r_{T-1}.
        values: V(s_0)..V(s_{T-1}), shape (T,); used detached.
        bootstrap: B (0 if the segment ended the episode).
        gamma: discount; tau: GAE lambda.

    Returns:
        (returns, advantages), each float32 (T,), without graph.
    """
    rl = torch.as_tensor(rewards, dtype=torch.float64).flatten().tolist()
    vl = values.detach().to(torch.float64).flatten().tolist()
    T = len(rl)
    if len(vl) != T:
        raise ValueError(f"{T} rewards but {len(vl)} values")
    returns = [0.0] * T
    advantages = [0.0] * T
    R = float(bootstrap)
    gae = 0.0
    next_v = float(bootstrap)
    for t in range(T - 1, -1, -1):
        R = rl[t] + gamma * R
        delta = rl[t] + gamma * next_v - vl[t]
        gae = gae * gamma * tau + delta
        returns[t] = R
        advantages[t] = gae
        next_v = vl[t]
    return (torch.tensor(returns, dtype=torch.float32),
            torch.tensor(advantages, dtype=torch.float32))


def actor_critic_loss(logits: torch.Tensor, values: torch.Tensor, actions: Sequence[int] |
                      torch.Tensor, rewards: Sequence[float] | torch.Tensor, bootstrap: float,
                      cfg: LossConfig | None = None) -> LossTerms:
    """L_AC over one segment of one episode.

    Args:
        logits: (T, A) or (T, 1, A) action logits with graph.
        values: (T,) or (T, 1) values with graph.
        actions: the actions taken, (T,).
        rewards: the rewards received, (T,).
        bootstrap: B, a float: 0 if the segment ended the episode, else the detached
            V(s_next) (see the module docstring and ``LossConfig.bootstrap_on_truncation``).
        cfg: gamma, tau, beta, value_coef (default :class:`LossConfig`).

    Returns:
        :class:`LossTerms`; call ``.total.backward()`` (or ``autograd.grad``).
    """
    cfg = cfg if cfg is not None else LossConfig()
    logits = logits.reshape(logits.shape[0], -1)
    values = values.reshape(-1)
    a = torch.as_tensor(actions, dtype=torch.long).reshape(-1)
    returns, advantages = returns_and_advantages(rewards, values, bootstrap, cfg.gamma, cfg.tau)
    log_probs = F.log_softmax(logits, dim=-1)
    entropy = -(log_probs.exp() * log_probs).sum(-1)                       # (T,)
    log_pi_a = log_probs.gather(1, a.unsqueeze(1)).squeeze(1)              # (T,)
    value_loss = (0.5 * (returns - values).pow(2)).sum()
    policy_loss = (-log_pi_a * advantages - cfg.beta * entropy).sum()
    total = policy_loss + cfg.value_coef * value_loss
    return LossTerms(total, policy_loss, value_loss, entropy.sum())
