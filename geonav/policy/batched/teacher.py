"""The curriculum's KL-prior teacher (ALGORITHMS.md (e), option A) for B slots at once.

As :class:`geonav.policy.teacher.Teacher`: the previous stage's frozen final policy,
with its own LSTM state per slot (zeroed at each episode start), fed the render at the
slot's current cell at the teacher's altitude and the target rendered there; its
log-probabilities enter lambda * KL(pi_T || pi_theta) in every interaction loss. The
teacher's image parts are computed once per view (its weights never change), from the
views of the same lattice at its altitude (the same view indices as the student's).

Beyond the paper's reading (the spec's ``loss``, ``schedule`` and ``weight0``): the term
may be the cross-entropy of the teacher's greedy action (DAgger-style distillation on the
student's own states), and lambda may hold until the student agrees with the teacher.
:meth:`BatchedTeacher.observe` keeps, over the acting steps, the agreement of the two
greedy actions and the KL, which the trainers report with each update.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
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
        self.agreed_at: int | None = None
        """Schedule 'agree': the stage episode at which the agreement was reached."""
        self.recent: deque[tuple[int, int]] = deque()  # (steps, agreeing steps) per call
        self.tally = [0, 0, 0.0]  # steps, agreeing steps, KL sum since the last report
        z = torch.zeros(n_slots, self.model.cfg.lstm_size, device=device)
        self.state: State = (z, z.clone(),
                             torch.zeros(n_slots, self.model.cfg.n_actions, device=device))

    @torch.no_grad()
    def step(self, view_idx: torch.Tensor, target_idx: torch.Tensor, start: torch.Tensor,
             feasible: np.ndarray | None = None) -> torch.Tensor:
        """(B, A) log pi_T at the slots' cells; ``start`` (B,) zeroes new episodes' state.
        ``feasible`` (B, A), the student's possible moves
        (:meth:`geonav.vecenv.LatticeVecEnv.feasible_moves`), renormalises pi_T over them
        with mask 'feasible' (a slot with none keeps pi_T whole)."""
        state = reset_state(self.state, start)
        logits, _, self.state = core_step(self.params, self.model.cfg.embed_dim, state,
                                          pre=self.tables.pre(view_idx, target_idx))
        if self.spec.mask == "feasible" and feasible is not None:
            ok = torch.from_numpy(np.asarray(feasible, bool)).to(logits.device)
            ok |= ~ok.any(-1, keepdim=True)
            logits = logits.masked_fill(~ok, -1e9)  # finite: 0 * log 0 stays 0 in the KL
        return torch.log_softmax(logits, dim=-1)

    def weight(self, episode: int) -> float:
        return float(self.spec.weight(episode, self.agreed_at))

    def terms(self, teacher_logp: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """(T, B) the teacher's term per step and slot before lambda: KL(pi_T || pi_theta),
        or with loss 'ce' -log pi_theta(argmax pi_T)."""
        if self.spec.loss == "ce":
            logp = torch.log_softmax(logits, dim=-1)
            return -logp.gather(-1, teacher_logp.argmax(-1, keepdim=True)).squeeze(-1)
        return kl_terms(teacher_logp, logits)

    @torch.no_grad()
    def observe(self, teacher_logp: torch.Tensor, logits: torch.Tensor, episode: int,
                mask: torch.Tensor | None = None, window: int = 2048) -> None:
        """Acting steps (T, B, A) each, ``mask`` (T, B) of live steps: tally the greedy
        agreement and the KL; schedule 'agree' marks ``episode`` (episodes done so far)
        once the last ``window`` steps agree at the spec's level."""
        same = (teacher_logp.argmax(-1) == logits.argmax(-1))
        kl = kl_terms(teacher_logp.to(logits.dtype), logits)
        if mask is not None:
            live = mask.bool()
            same, kl = same[live], kl[live]
        n, k = int(same.numel()), int(same.sum())
        self.tally[0] += n
        self.tally[1] += k
        self.tally[2] += float(kl.sum())
        self.recent.append((n, k))
        while sum(x for x, _ in self.recent) - self.recent[0][0] >= window:
            self.recent.popleft()
        steps = sum(x for x, _ in self.recent)
        if self.agreed_at is None and steps >= window and \
                sum(y for _, y in self.recent) >= self.spec.agree * steps:
            self.agreed_at = int(episode)

    def report(self) -> dict[str, float]:
        """The agreement and mean KL per step since the last report (the metrics of an
        update), and the episode at which schedule 'agree' was met (-1: not yet)."""
        n, k, kl = self.tally
        self.tally = [0, 0, 0.0]
        return {"teacher_agree": k / n if n else float("nan"),
                "teacher_kl": kl / n if n else float("nan"),
                "teacher_agreed_at": -1 if self.agreed_at is None else self.agreed_at}


def kl_terms(teacher_logp: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """(T, B) KL(pi_T || pi_theta) per step and slot, from (T, B, A) each."""
    logp = torch.log_softmax(logits, dim=-1)
    return (teacher_logp.exp() * (teacher_logp - logp)).sum(-1)
