"""Functional pieces shared by SAVN, ISAR and the curriculum teacher.

* :func:`segment_forward`: one stored segment recomputed in a single batched
  ``torch.func.functional_call`` from a start state, with the graph (and, on request,
  the per-step LSTM outputs h, which SAVN's learned loss reads);
* :class:`Segment`: a stored segment (an A3C :class:`~geonav.policy.a3c.Rollout` plus
  the teacher's log-probabilities for the KL prior);
* :func:`segment_loss`: L_AC of a segment (ALGORITHMS.md 4.0), plus lambda KL(pi_T || pi)
  when a teacher is present (ALGORITHMS.md (e), option A);
* :func:`sgd_step`: theta' = theta - alpha g, differentiable (plain tensors).

Acting happens under ``no_grad`` on a plain module loaded with theta's values
(:func:`load_values`); the loss recomputes the segment from its stored start state, so
the numbers equal a graph kept per step (tested in ``tests/test_meta_isar.py``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn
from torch.nn import functional as F

from geonav.policy.a3c import Rollout
from geonav.policy.config import LossConfig
from geonav.policy.losses import actor_critic_loss
from geonav.policy.model import ActorCritic, State

Params = dict[str, torch.Tensor]


@dataclass
class Segment(Rollout):
    """A stored segment: start state, target, views, actions, rewards, and per step the
    teacher's log-probabilities (empty without a teacher) and the previous-altitude views
    of the extra input slot (empty: zero-filled)."""

    teacher_logp: list[torch.Tensor] = field(default_factory=list)
    prev_views: list[torch.Tensor] = field(default_factory=list)

    def prev(self) -> torch.Tensor | None:
        """(T, ...) previous-altitude views, or None (zero-filled slot / no slot)."""
        return torch.stack(self.prev_views) if self.prev_views else None


@dataclass
class SegmentOut:
    """What :func:`segment_loss` returns."""

    loss: torch.Tensor
    """L_AC (+ lambda KL) with graph."""
    terms: Any
    """The :class:`~geonav.policy.losses.LossTerms` of L_AC."""
    logits: torch.Tensor
    """(T, A) with graph."""
    values: torch.Tensor
    """(T,) with graph."""
    hidden: torch.Tensor | None
    """(T, lstm_size) LSTM outputs with graph (when asked for)."""
    end_state: State
    """The state after the segment, with graph."""


@contextlib.contextmanager
def capture_hidden(model: ActorCritic) -> Iterator[list[torch.Tensor]]:
    """Collect the LSTM outputs of ``model.forward``: its critic head is applied once to
    the stacked per-step h, (T, B, lstm_size), which a forward hook records."""
    seen: list[torch.Tensor] = []
    handle = model.critic.register_forward_hook(lambda m, inp, out: seen.append(inp[0]))
    try:
        yield seen
    finally:
        handle.remove()


def segment_forward(model: ActorCritic, params: Params | None, views: torch.Tensor,
                    target: torch.Tensor, state: State, hidden: bool = False,
                    prev: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, State]:
    """T steps of one episode in one call.

    Args:
        views: (T, ...) current views (uint8 images or features).
        target: (...) the target view.
        state: the state before the first step.
        params: name -> tensor for ``functional_call`` (None: the module's own).
        hidden: also return the per-step LSTM outputs.
        prev: (T, ...) previous-altitude views for the extra slot (None: zero-filled).

    Returns:
        logits (T, A), values (T,), h (T, lstm_size) or None, end state.
    """
    args: tuple[Any, ...] = (views.unsqueeze(1), target.unsqueeze(0), state)
    if prev is not None:
        args = (*args, prev.unsqueeze(1))
    with capture_hidden(model) if hidden else contextlib.nullcontext([]) as seen:
        if params is None:
            logits, values, end = model(*args)
        else:
            logits, values, end = torch.func.functional_call(model, params, args, strict=True)
    hs = seen[-1][:, 0] if hidden else None
    return logits[:, 0], values[:, 0], hs, end


def teacher_kl(teacher_logp: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """sum_t KL(pi_T || pi_theta) = sum_t sum_a p_T (log p_T - log pi_theta); (T, A) each."""
    logp = F.log_softmax(logits, dim=-1)
    return (teacher_logp.exp() * (teacher_logp - logp)).sum()


def segment_loss(model: ActorCritic, params: Params | None, seg: Segment, bootstrap: float,
                 loss_cfg: LossConfig, state: State | None = None, *, hidden: bool = False,
                 kl_weight: float = 0.0) -> SegmentOut:
    """L_AC of a stored segment recomputed from ``state`` (default: its stored start state),
    plus ``kl_weight`` * KL to the teacher when the segment holds teacher log-probs."""
    views = torch.stack(seg.views)
    logits, values, hs, end = segment_forward(
        model, params, views, seg.target, seg.start_state if state is None else state, hidden,
        seg.prev())
    terms = actor_critic_loss(logits, values, seg.actions, seg.rewards, bootstrap, loss_cfg)
    loss = terms.total
    if kl_weight > 0.0 and seg.teacher_logp:
        loss = loss + kl_weight * teacher_kl(torch.stack(seg.teacher_logp).to(logits.dtype),
                                             logits)
    return SegmentOut(loss, terms, logits, values, hs, end)


def sgd_step(params: Params, loss: torch.Tensor, lr: float, *, create_graph: bool,
             names: list[str] | None = None) -> Params:
    """theta' = theta - lr * d loss / d theta over ``names`` (default: all), as new tensors.

    ``retain_graph=True`` always: later losses share graph with this one (through h and
    the stored window losses), even in first order (ALGORITHMS.md "Differentiable inner
    updates"). In first order the gradient is a constant, so d theta'/d theta = I.
    """
    names = list(params) if names is None else names
    grads = torch.autograd.grad(loss, [params[n] for n in names], create_graph=create_graph,
                                retain_graph=True, allow_unused=True)
    out = dict(params)
    for n, g in zip(names, grads, strict=True):
        if g is not None:
            out[n] = params[n] - lr * g
    return out


def grads_of(loss: torch.Tensor, leaves: list[torch.Tensor]) -> list[torch.Tensor]:
    """d loss / d leaves, zeros for unused leaves (the graph is freed), each in its leaf's
    memory layout.

    ``autograd.grad`` may return a gradient with other strides than its leaf (the learned
    loss's first convolution: (2, 20, 1) against (6, 2, 1)); ``.backward()`` would copy it
    into the leaf's layout, and torch's fused Adam kernel (torch 2.13, CPU) steps a
    parameter with its gradient elementwise in memory order, so a gradient set as
    ``.grad`` in another layout would move the wrong elements.
    """
    gs = torch.autograd.grad(loss, leaves, allow_unused=True)
    return [torch.zeros_like(p) if g is None else
            g if g.stride() == p.stride() else torch.empty_like(p).copy_(g)
            for p, g in zip(leaves, gs, strict=True)]


def load_values(module: nn.Module, params: Params) -> None:
    """Copy ``params``' values into ``module``'s parameters (for acting under no_grad)."""
    with torch.no_grad():
        mine = dict(module.named_parameters())
        names = [n for n in params if n in mine]
        torch._foreach_copy_([mine[n] for n in names], [params[n].detach() for n in names])


def encoder_params(params: Params) -> Params:
    return {k[len("encoder."):]: v for k, v in params.items() if k.startswith("encoder.")}
