"""SharedAdam: torch's Adam with its state in shared memory (allenai/savn, ikostrikov/pytorch-a3c).

The state is created eagerly and moved to shared memory, so every worker
process that receives the optimiser steps the same moments and step counts
(Hogwild, no locks). Stepping is torch's own Adam (``fused=True`` where it
helps: several times faster on CPU), so there is no hand-written update rule.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import torch


class SharedAdam(torch.optim.Adam):
    """Adam whose state tensors live in shared memory.

    Defaults follow SAVN's SharedAdam: lr 1e-4, betas (0.9, 0.999), eps 1e-3, amsgrad.
    """

    def __init__(self, params: Iterable[torch.Tensor], lr: float = 1e-4,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-3,
                 weight_decay: float = 0.0, amsgrad: bool = True, fused: bool = True) -> None:
        super().__init__(params, lr=lr, betas=betas, eps=eps, weight_decay=weight_decay,
                         amsgrad=amsgrad, fused=fused or None)
        self.init_state()
        self.share_memory()

    def init_state(self) -> None:
        """Create the state torch's Adam would create lazily (so it can be shared)."""
        for group in self.param_groups:
            for p in group["params"]:
                state = self.state[p]
                if len(state) > 0:
                    continue
                state["step"] = torch.zeros((), dtype=torch.float32)
                state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                if group["amsgrad"]:
                    state["max_exp_avg_sq"] = torch.zeros_like(
                        p, memory_format=torch.preserve_format)

    def share_memory(self) -> SharedAdam:
        for group in self.param_groups:
            for p in group["params"]:
                for v in self.state[p].values():
                    if isinstance(v, torch.Tensor):
                        v.share_memory_()
        return self

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        super().load_state_dict(state_dict)
        self.init_state()
        for group in self.param_groups:  # loaded steps may come back as non-float32 scalars
            for p in group["params"]:
                st = self.state[p]
                if isinstance(st.get("step"), torch.Tensor):
                    st["step"] = st["step"].to(torch.float32).reshape(())
        self.share_memory()


def warm_up_lr(optimizer: torch.optim.Optimizer, lr: float, warmup: int) -> None:
    """Set every group's rate for the coming step: ``lr * min(1, (n + 1) / warmup)``, where
    n is the number of steps the optimiser has taken (read from its state, so a resumed run
    continues its ramp). ``warmup <= 0`` leaves the rate at ``lr``.

    Fine-tuning a trained policy with a fresh Adam moves every weight by about ``lr`` on
    each of the first steps, whatever its gradient (Adam divides by the root of its
    second-moment estimate, which starts from the first gradients themselves); a linear
    ramp keeps those first steps small.
    """
    if warmup <= 0:
        return
    n = 0
    for group in optimizer.param_groups:
        for p in group["params"]:
            step = optimizer.state.get(p, {}).get("step")
            if step is not None:
                n = int(step.item() if isinstance(step, torch.Tensor) else step)
            break
        break
    scale = min(1.0, (n + 1) / warmup)
    for group in optimizer.param_groups:
        group["lr"] = lr * scale
