"""The curriculum's KL-prior teacher (ALGORITHMS.md (e), option A).

The teacher is the previous stage's frozen final policy with its own LSTM state. At
every step it sees the render at the student's current cell at *its* altitude (the
lattice is the same at every altitude, so a cell names the same place) and the target
rendered at that altitude; its action log-probabilities go into the segment, and the
student's interaction loss gains lambda * KL(pi_T || pi_theta).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from geonav.policy.agent import view_input
from geonav.policy.checkpoint import check_compatible, load_checkpoint
from geonav.policy.meta_config import kl_weight


@dataclass(frozen=True)
class TeacherSpec:
    """A picklable recipe for a teacher (built once per worker process).

    Attributes:
        checkpoint: the teacher policy (previous stage's final checkpoint).
        env_factory: the stage's environment at the teacher's altitude (same tasks).
        budget: the stage's episode budget (lambda's schedule).
        fraction: lambda falls from 1 to 0 over this fraction of ``budget``.
    """

    checkpoint: str
    env_factory: Any
    budget: int
    fraction: float = 0.25

    def build(self) -> Teacher:
        return Teacher(self)

    def weight(self, episode: int) -> float:
        """lambda at a stage episode (1-based)."""
        return kl_weight(episode, self.budget, self.fraction)


class Teacher:
    """Acts alongside the student and returns its log-probabilities (no gradients)."""

    def __init__(self, spec: TeacherSpec) -> None:
        ckpt = load_checkpoint(spec.checkpoint)
        self.spec = spec
        self.env = spec.env_factory()
        check_compatible(ckpt.meta, self.env, path=ckpt.path)
        self.model = ckpt.build_model().requires_grad_(False)
        self.frozen = ckpt.build_encoder()
        self.state = self.model.initial_state()
        self.target: torch.Tensor | None = None
        self.task_index = -1

    def _view(self, task_index: int, cell: tuple[int, int]) -> torch.Tensor:
        u = self.env.unwrapped
        alt = float(u.tasks[task_index].alt_m)
        key = (task_index, (int(cell[0]), int(cell[1])), alt) if self.frozen is not None \
            else None
        return view_input(u.observation_at(task_index, (int(cell[0]), int(cell[1]))),
                          self.frozen, key)

    def reset(self, info: dict[str, Any]) -> None:
        """A new episode: zero state, the target rendered at the teacher's altitude."""
        self.task_index = int(info["task_index"])
        self.state = self.model.initial_state()
        self.target = self._view(self.task_index, tuple(info["target_cell"]))

    @torch.no_grad()
    def step(self, info: dict[str, Any]) -> torch.Tensor:
        """log pi_T(. | render at info's cell at the teacher's altitude), (A,)."""
        x = self._view(self.task_index, tuple(info["cell"]))
        assert self.target is not None
        logits, _, self.state = self.model(x[None, None], self.target[None], self.state)
        return torch.log_softmax(logits[0, 0], dim=-1)
