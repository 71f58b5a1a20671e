"""The per-slot pieces of batched meta-training (:mod:`geonav.policy.batched.meta`): an
Adam over stacked per-slot parameters (:class:`SlotAdam`), per-slot gradient clipping and
layout, and the view embeddings' per-slot bases of one window (:class:`ViewBases`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from geonav.policy.batched.core import AtPsi
from geonav.vecenv import LatticeVecEnv


class SlotAdam:
    """Adam over stacked per-slot parameters (B, ...) with a step count per slot.

    A step moves only the live slots, so each slot's moments and bias corrections are
    those of its own ``torch.optim.Adam`` (the reference's fresh in-task Adam per task
    visit), also when the slots' episodes end at different windows and the next episode
    of the visit (E > 1) goes on with them. The update is torch's fused Adam kernel
    (``torch._fused_adam_``, L2-free, the reference's default ``fused = True``), called
    once per window on every live slot's views of every parameter (slot s's rows of the
    stacked tensors, with slot s's step count): one pass over the memory, where the
    elementwise form took about a dozen and 40 % of a meta-iteration.

    ``warmup`` > 0 ramps each slot's rate as :func:`~geonav.policy.optim.warm_up_lr` ramps
    the reference's per-visit Adam (``lr_warmup``): slot s's k-th step runs at
    lr * min(1, k / warmup), k read from its own step count, so slots that have stepped
    different numbers of times step at their own rates (one kernel call per distinct rate).
    """

    def __init__(self, params: list[torch.Tensor], lr: float, betas: tuple[float, float],
                 eps: float, amsgrad: bool, warmup: int = 0) -> None:
        self.params, self.lr, self.betas, self.eps, self.amsgrad = params, lr, betas, eps, \
            amsgrad
        self.warmup = int(warmup)
        b = params[0].shape[0]
        # one 0-dim step tensor per slot, float32 as torch's fused Adam keeps its steps
        self.steps = [torch.zeros((), dtype=torch.float32, device=params[0].device)
                      for _ in range(b)]
        self.m = [torch.zeros_like(p) for p in params]
        self.v = [torch.zeros_like(p) for p in params]
        self.v_max = [torch.zeros_like(p) for p in params] if amsgrad else []
        # slot s's rows of every parameter and moment (views, so the kernel writes in place)
        self._views = [self._slot_views(s) for s in range(b)]

    def _slot_views(self, s: int) -> tuple[list[torch.Tensor], ...]:
        return ([p.detach()[s] for p in self.params], [m[s] for m in self.m],
                [v[s] for v in self.v], [v[s] for v in self.v_max])

    def reset(self) -> None:
        """Step 0, zero moments (a fresh Adam for every slot)."""
        torch._foreach_zero_([*self.steps, *self.m, *self.v, *self.v_max])

    @torch.no_grad()
    def step(self, grads: list[torch.Tensor], slots: list[int]) -> None:
        """One Adam step of the slots ``slots`` with ``grads`` (len(slots), ...), row i
        slot ``slots[i]``'s (contiguous, as the parameters)."""
        groups: dict[float, tuple[list[torch.Tensor], ...]] = {}
        for i, s in enumerate(slots):
            lr = self.slot_lr(s)  # from the steps taken before this one, as warm_up_lr
            self.steps[s].add_(1.0)
            params, gs, ms, vs, vm, steps = groups.setdefault(lr, ([], [], [], [], [], []))
            p, m, v, w = self._views[s]
            params += p
            gs += [g[i] for g in grads]
            ms += m
            vs += v
            vm += w
            steps += [self.steps[s]] * len(p)
        b1, b2 = self.betas
        for lr, (params, gs, ms, vs, vm, steps) in groups.items():
            torch._fused_adam_(params, gs, ms, vs, vm, steps, amsgrad=self.amsgrad, lr=lr,
                               beta1=b1, beta2=b2, weight_decay=0.0, eps=self.eps,
                               maximize=False, grad_scale=None, found_inf=None)

    def slot_lr(self, s: int) -> float:
        """The rate of slot ``s``'s next step: ``lr * min(1, (n + 1) / warmup)`` with n its
        steps so far (:func:`~geonav.policy.optim.warm_up_lr`'s ramp), or ``lr``."""
        if self.warmup <= 0:
            return self.lr
        n = int(self.steps[s].item())
        return self.lr * min(1.0, (n + 1) / self.warmup)


def psi_layout(g: torch.Tensor) -> torch.Tensor:
    """One slot's gradient in its parameter's layout (weights are stored transposed)."""
    return g.t().contiguous() if g.dim() == 2 else g


def clip_per_slot(grads: list[torch.Tensor], max_norm: float) -> None:
    """``nn.utils.clip_grad_norm_`` of each slot's gradients (dim 0 of every tensor), in
    place: slot s is scaled by min(1, max_norm / (|g_s| + 1e-6))."""
    if not max_norm:
        return
    norms = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g.flatten(1), dim=1)
                                                  for g in grads]), dim=0)
    coef = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    for g in grads:
        g.mul_(coef.view(-1, *([1] * (g.dim() - 1))))


class ViewBases:
    """The view embeddings' W_s x + b_s of one window under per-slot phi^s, without graph,
    and their gradients from the output gradients.

    The current view's are a table of every view of the slot's (pinned) task, one batched
    product per window, when the largest task has at most ``views_per_step`` views per
    step of the window (meta.PRE_TABLE_VIEWS_PER_STEP); else one per step. Each step's rows and
    the window's target rows become leaves whose gradients give
    dW_s = sum_t u_t x_t^T (the inputs are constant feature rows).
    """

    def __init__(self, phi: dict[str, torch.Tensor], table: torch.Tensor,
                 venv: LatticeVecEnv, schedule: tuple[int, int], rows: np.ndarray,
                 views_per_step: int) -> None:
        self.phi, self.table = phi, table
        self.slots = torch.arange(len(rows), device=table.device)
        tasks = venv.task[rows]
        sizes = venv.nx[tasks] * venv.ny[tasks]
        # with imagery variants, row k * n_cells + v is view v under variant k, and an
        # episode keeps its variant (geonav.vecenv): the slots' views and targets are read
        # from their episode's variant, as slot_indices() gives them
        first = venv.variant[rows] * venv.n_cells + venv.offsets[tasks]
        self.first = torch.from_numpy(first).to(table.device)
        w, bias = phi["obs_embed.weight"].detach(), phi["obs_embed.bias"].detach()
        shared = isinstance(phi, AtPsi)  # psi's (out, in) weights for every slot
        self.pre: torch.Tensor | None = None
        # one (C, F) x (F, E) product per slot and window runs at the arithmetic's speed,
        # a row per step at memory speed (it reads the slot's (F, E) weights each time):
        # measured here, the table of C views costs about C / 20 steps' products, and it
        # keeps the per-step working set (the other layers' weights of every slot) in cache
        if int(sizes.max()) <= views_per_step * schedule[0] * schedule[1]:
            cells = self.first[:, None] + torch.arange(int(sizes.max()), device=table.device)
            cells = torch.minimum(cells, torch.from_numpy(first + sizes - 1)
                                  .to(table.device)[:, None])
            if not shared:
                self.pre = torch.baddbmm(bias.unsqueeze(1), table[cells], w)
            elif table.shape[0] <= cells.numel():  # psi's: each view once, then gathered
                self.pre = torch.nn.functional.linear(table, w)[cells] + bias.unsqueeze(1)
            else:
                self.pre = torch.nn.functional.linear(table[cells], w) + bias.unsqueeze(1)
        tgt = torch.from_numpy(venv.target_index[rows]).to(table.device)
        self.target_rows = tgt
        wt, bt = phi["target_embed.weight"].detach(), phi["target_embed.bias"].detach()
        self.target = torch.baddbmm(bt.unsqueeze(1), table[tgt].unsqueeze(1), wt).squeeze(1) \
            if not shared else torch.nn.functional.linear(table[tgt], wt) + bt
        self.target.requires_grad_()
        self.obs_leaves: list[torch.Tensor] = []
        self.obs_rows: list[torch.Tensor] = []

    def obs(self, vi: torch.Tensor, leaf: bool) -> torch.Tensor:
        """(B, E) W_s x + b_s of the slots' current views ``vi`` (with ``leaf``: kept for
        the window's gradient)."""
        if self.pre is not None:
            y = self.pre[self.slots, vi - self.first]
        else:
            w, bias = self.phi["obs_embed.weight"].detach(), self.phi["obs_embed.bias"].detach()
            y = torch.nn.functional.linear(self.table[vi], w) + bias \
                if isinstance(self.phi, AtPsi) else \
                torch.baddbmm(bias.unsqueeze(1), self.table[vi].unsqueeze(1), w).squeeze(1)
        if not leaf:
            return y
        y = y.detach().requires_grad_()
        self.obs_leaves.append(y)
        self.obs_rows.append(vi)
        return y

    def leaves(self) -> list[torch.Tensor]:
        return [*self.obs_leaves, self.target]

    def grads(self, gs: Any) -> dict[str, torch.Tensor]:
        """Parameter name -> (B, ...) gradient from the gradients of :meth:`leaves`."""
        z = torch.zeros_like(self.target)
        u = torch.stack([z if g is None else g for g in gs[:-1]], 1)        # (B, T, E)
        x = self.table[torch.stack(self.obs_rows, 1)]                      # (B, T, F)
        ut = z if gs[-1] is None else gs[-1]
        return {"obs_embed.weight": torch.bmm(x.transpose(1, 2), u),          # (B, F, E)
                "obs_embed.bias": u.sum(1),
                "target_embed.weight": torch.bmm(self.table[self.target_rows].unsqueeze(-1),
                                                 ut.unsqueeze(1)), "target_embed.bias": ut}


__all__ = ["SlotAdam", "ViewBases", "clip_per_slot", "psi_layout"]
