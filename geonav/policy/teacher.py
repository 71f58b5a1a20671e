"""The curriculum's KL-prior teacher (ALGORITHMS.md (e), option A), and the source of the
previous-altitude view of option B (the extra input slot E(o^prev)).

The teacher is the previous stage's frozen final policy with its own LSTM state. At
every step it sees the render at the student's current cell at *its* altitude (the
lattice is the same at every altitude, so a cell names the same place) and the target
rendered at that altitude; its action log-probabilities go into the segment, and the
student's interaction loss gains lambda * KL(pi_T || pi_theta).

Option B (:class:`PrevViewSpec` / :class:`PrevViewSource`) renders the same view, the
student's cell at the previous altitude, but feeds it to the *student* network's extra
slot, encoded exactly as the current view (the student's own encoder; the frozen
feature cache keyed by task, cell and altitude). The target input is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from geonav.policy.agent import view_input
from geonav.policy.checkpoint import check_compatible, load_checkpoint
from geonav.policy.encoders import FrozenEncoder
from geonav.policy.meta_config import kl_weight

ASYNC_TEACHER = ("the curriculum teacher's schedule 'agree', loss 'ce', mask 'feasible' and "
                 "weights other than 1 run on engine = 'batched' only (schedule 'agree' and "
                 "mask 'feasible' are the defaults); on the async engine set "
                 "teacher_schedule = 'linear' and teacher_mask = 'none' (the paper's reading)")


@dataclass(frozen=True)
class TeacherSpec:
    """A picklable recipe for a teacher (built once per worker process).

    Attributes:
        checkpoint: the teacher policy (previous stage's final checkpoint).
        env_factory: the stage's environment at the teacher's altitude (same tasks).
        budget: the stage's episode budget (lambda's schedule).
        fraction: lambda falls from 1 to 0 over this fraction of ``budget``.
        weight0: lambda's starting value.
        schedule: 'linear' or 'agree' (:class:`geonav.policy.meta_config.CurriculumConfig`;
            'agree' is the batched engine's, :class:`~geonav.policy.batched.teacher.
            BatchedTeacher`).
        loss: 'kl' or 'ce' (the same; 'ce' batched only).
        agree: the agreement at which schedule 'agree' lets lambda fall.
        mask: 'none' or 'feasible' (the teacher renormalised over the student's possible
            moves; batched only).
    """

    checkpoint: str
    env_factory: Any
    budget: int
    fraction: float = 0.25
    weight0: float = 1.0
    schedule: str = "linear"
    loss: str = "kl"
    agree: float = 0.9
    mask: str = "none"

    def build(self) -> Teacher:
        if not self.is_paper:
            from geonav.errors import ConfigError

            raise ConfigError(ASYNC_TEACHER)
        return Teacher(self)

    @property
    def is_paper(self) -> bool:
        """The paper's reading: lambda 1 -> 0 linearly, KL, no mask."""
        return (self.schedule, self.loss, self.weight0, self.mask) == \
            ("linear", "kl", 1.0, "none")

    def weight(self, episode: int, agreed_at: int | None = None) -> float:
        """lambda at a stage episode (1-based). Schedule 'agree': ``weight0`` until the
        episode ``agreed_at`` at which the agreement was reached (None: not yet), then
        falling to 0 over the same span as 'linear'."""
        if self.schedule == "agree":
            if agreed_at is None or episode <= agreed_at:
                return self.weight0
            return self.weight0 * kl_weight(episode - agreed_at, self.budget, self.fraction)
        return self.weight0 * kl_weight(episode, self.budget, self.fraction)


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
        return view_at(self.env, self.frozen, task_index, cell)

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


def view_at(env: Any, frozen: FrozenEncoder | None, task_index: int,
            cell: tuple[int, int]) -> torch.Tensor:
    """The network input of the render at ``cell`` of task ``task_index`` in ``env`` (at
    that env's altitude): uint8 image, or frozen features through the cache."""
    u = env.unwrapped
    c = (int(cell[0]), int(cell[1]))
    alt = float(u.tasks[task_index].alt_m)
    key = (u.task_key(task_index), c, alt) if frozen is not None else None
    target = None
    if frozen is not None and frozen.pairwise:
        target = u.observation_at(task_index, tuple(u.tasks[task_index].target_cell))
    return view_input(u.observation_at(task_index, c), frozen, key, target)


@dataclass(frozen=True)
class PrevViewSpec:
    """A picklable recipe for the previous-altitude view of option B (built per worker).

    Attributes:
        env_factory: the stage's environment at the previous stage's altitude (same tasks,
            same lattice).
        alt_m: that altitude (recorded in config.json).
    """

    env_factory: Any
    alt_m: float

    def build(self, frozen: FrozenEncoder | None) -> PrevViewSource:
        """The source, encoding with the student's frozen encoder (None: uint8 images for
        the student's trainable CNN)."""
        return PrevViewSource(self, frozen)


class PrevViewSource:
    """Gives, per step, the student's network input for the view at the student's current
    cell rendered at the previous altitude (the extra slot's input)."""

    def __init__(self, spec: PrevViewSpec, frozen: FrozenEncoder | None) -> None:
        self.spec = spec
        self.env = spec.env_factory()
        self.frozen = frozen
        self.task_index = -1

    def reset(self, info: dict[str, Any]) -> None:
        """A new episode (remembers the task)."""
        self.task_index = int(info["task_index"])

    def view(self, info: dict[str, Any]) -> torch.Tensor:
        """The input for ``info``'s cell: (N, N, 3) uint8 or (F,) features."""
        return view_at(self.env, self.frozen, self.task_index, tuple(info["cell"]))
