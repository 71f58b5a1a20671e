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

import numpy as np
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


def gae_returns(rewards: np.ndarray, values: np.ndarray, bootstrap: np.ndarray,
                ends: np.ndarray | None, gamma: float, tau: float,
                end_values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Discounted returns and GAE advantages of (T, B) step sequences, float64.

    The one implementation of the recursion: the reference trainers call it with B = 1
    and no episode end inside the segment (:func:`returns_and_advantages`), the batched
    engine with B slots whose sequences may contain episode ends (masked GAE).

    Args:
        rewards: (T, B) r_t.
        values: (T, B) detached V(s_t).
        bootstrap: (B,) B after the last step (0 where the last step ended the episode).
        ends: (T, B) bool, step t ended slot b's episode (nothing is bootstrapped past
            it: R and the GAE restart from 0 before step t); None: no ends inside.
        gamma: discount; tau: GAE lambda.
        end_values: (T, B) the value bootstrapped at an episode end instead of 0 (a
            time-limit truncation with ``LossConfig.bootstrap_on_truncation``).
    """
    T = rewards.shape[0]
    returns = np.zeros_like(values, dtype=np.float64)
    advantages = np.zeros_like(values, dtype=np.float64)
    R = np.asarray(bootstrap, np.float64).copy()
    next_v = R.copy()
    gae = np.zeros_like(R)
    for t in range(T - 1, -1, -1):
        if ends is not None and ends[t].any():
            e = ends[t]
            R[e] = 0.0 if end_values is None else end_values[t][e]
            next_v[e] = R[e]
            gae[e] = 0.0
        R = rewards[t] + gamma * R
        delta = rewards[t] + gamma * next_v - values[t]
        gae = gae * gamma * tau + delta
        returns[t] = R
        advantages[t] = gae
        next_v = values[t].copy()
    return returns, advantages


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
        (returns, advantages), each (T,) in the dtype of ``values``, without graph.
    """
    rl = torch.as_tensor(rewards, dtype=torch.float64).detach().cpu().numpy().reshape(-1, 1)
    vl = values.detach().to(torch.float64).cpu().numpy().reshape(-1, 1)
    if len(vl) != len(rl):
        raise ValueError(f"{len(rl)} rewards but {len(vl)} values")
    returns, advantages = gae_returns(rl, vl, np.array([float(bootstrap)]), None, gamma, tau)
    return (torch.from_numpy(returns[:, 0]).to(values.dtype),
            torch.from_numpy(advantages[:, 0]).to(values.dtype))


def clipped_surrogate(log_pi_a: torch.Tensor, old_log_pi_a: torch.Tensor,
                      advantages: torch.Tensor, clip_coef: float) -> torch.Tensor:
    """PPO's per-step clipped surrogate loss (Schulman et al. 2017, Eq. 7, negated):
    -min(rho A, clip(rho, 1 - eps, 1 + eps) A), rho = exp(log pi(a) - log pi_old(a)).

    Its gradient is -rho A grad log pi(a) where the clip is inactive, 0 where it is
    active; at rho = 1 (the policy that acted) it is the A3C term -A grad log pi(a).

    Args:
        log_pi_a: (...) log pi(a_t | s_t) with graph.
        old_log_pi_a: (...) the acting policy's log pi_old(a_t | s_t), constants.
        advantages: (...) constants; clip_coef: epsilon.
    """
    ratio = (log_pi_a - old_log_pi_a).exp()
    return torch.max(-advantages * ratio,
                     -advantages * ratio.clamp(1.0 - clip_coef, 1.0 + clip_coef))


def policy_value_terms(logits: torch.Tensor, values: torch.Tensor, actions: torch.Tensor,
                       returns: torch.Tensor, advantages: torch.Tensor, cfg: LossConfig,
                       weights: torch.Tensor | None = None,
                       old_log_probs: torch.Tensor | None = None,
                       clip_coef: float = 0.2) -> LossTerms:
    """The per-step terms of L_AC summed (optionally weighted per step).

    With ``old_log_probs`` the policy term is PPO's clipped surrogate
    (:func:`clipped_surrogate`) instead of -log pi(a) A: the ISAR PPO base's segment loss
    (``ISARConfig.base_loss = 'ppo'``, docs/learning.md).

    Args:
        logits: (..., A) with graph; values: (...) with graph.
        actions, returns, advantages: (...) constants.
        weights: (...) per-step weights (the batched engine's masks / B); None: 1.
        old_log_probs: (...) log pi_old(a_t) of the policy that acted, constants; None:
            the A3C policy-gradient term.
        clip_coef: epsilon of the clipped surrogate (with ``old_log_probs``).
    """
    log_probs = F.log_softmax(logits, dim=-1)
    entropy = -(log_probs.exp() * log_probs).sum(-1)                       # (...)
    log_pi_a = log_probs.gather(-1, actions.unsqueeze(-1)).squeeze(-1)     # (...)
    value_step = 0.5 * (returns - values).pow(2)
    if old_log_probs is None:
        policy_step = -log_pi_a * advantages - cfg.beta * entropy
    else:
        policy_step = clipped_surrogate(log_pi_a, old_log_probs, advantages, clip_coef) \
            - cfg.beta * entropy
    if weights is not None:
        value_step, policy_step, entropy = (value_step * weights, policy_step * weights,
                                            entropy * weights)
    value_loss = value_step.sum()
    policy_loss = policy_step.sum()
    total = policy_loss + cfg.value_coef * value_loss
    return LossTerms(total, policy_loss, value_loss, entropy.sum())


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
    return policy_value_terms(logits, values, a, returns, advantages, cfg)
