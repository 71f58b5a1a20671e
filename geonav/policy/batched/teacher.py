"""The curriculum's KL-prior teacher (ALGORITHMS.md (e), option A) for B slots at once.

As :class:`geonav.policy.teacher.Teacher`: the previous stage's frozen final policy,
with its own LSTM state per slot (zeroed at each episode start), fed the render at the
slot's current cell at the teacher's altitude and the target rendered there; its
log-probabilities enter lambda * KL(pi_T || pi_theta) in every interaction loss. The
teacher's image parts are computed once per view (its weights never change), from the
views of the same lattice at its altitude (the same view indices as the student's).
"""

from __future__ import annotations

from typing import Any

import torch

from geonav.policy.batched.core import ActingTables, core_step, reset_state
from geonav.policy.checkpoint import check_compatible, load_checkpoint
from geonav.policy.model import State
from geonav.vecenv import LatticeVecEnv


class BatchedTeacher:
    """Steps the teacher for B slots (no gradients); see the module docstring."""

    def __init__(self, spec: Any, n_slots: int, device: torch.device) -> None:
        ckpt = load_checkpoint(spec.checkpoint)
        self.spec = spec
        env = spec.env_factory()
        check_compatible(ckpt.meta, env, path=ckpt.path)
        self.model = ckpt.build_model().requires_grad_(False).to(device)
        frozen = ckpt.build_encoder()
        venv = LatticeVecEnv(env, 1)
        if frozen is not None:
            table = venv.feature_table(frozen).to(device)
            features = table.__getitem__
        else:
            images = torch.from_numpy(venv.image_table()).to(device)

            def features(rows: torch.Tensor) -> torch.Tensor:
                return self.model.features(images[rows])
        self.params: dict[str, torch.Tensor] = dict(self.model.named_parameters())
        self.tables = ActingTables(self.params, self.model.cfg.embed_dim, venv.n_views,
                                   features)
        z = torch.zeros(n_slots, self.model.cfg.lstm_size, device=device)
        self.state: State = (z, z.clone(),
                             torch.zeros(n_slots, self.model.cfg.n_actions, device=device))

    @torch.no_grad()
    def step(self, view_idx: torch.Tensor, target_idx: torch.Tensor,
             start: torch.Tensor) -> torch.Tensor:
        """(B, A) log pi_T at the slots' cells; ``start`` (B,) zeroes new episodes' state."""
        state = reset_state(self.state, start)
        logits, _, self.state = core_step(self.params, self.model.cfg.embed_dim, state,
                                          pre=self.tables.pre(view_idx, target_idx))
        return torch.log_softmax(logits, dim=-1)

    def weight(self, episode: int) -> float:
        return float(self.spec.weight(episode))


def kl_terms(teacher_logp: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """(T, B) KL(pi_T || pi_theta) per step and slot, from (T, B, A) each."""
    logp = torch.log_softmax(logits, dim=-1)
    return (teacher_logp.exp() * (teacher_logp - logp)).sum(-1)
