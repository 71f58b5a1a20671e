"""Configuration of SAVN, ISAR, meta-training and the curriculum (ALGORITHMS.md (b)-(e)).

SAVN and ISAR configs extend :class:`~geonav.policy.config.A3CConfig`: they run on the
A3C trainer's machinery (workers, shared Adam, checkpoints, metrics), so ``episodes``,
``workers``, ``lr`` (the outer/adaptive learning rate), ``seed`` and the rest mean the
same. Every interpretation of the paper is a named field here and is written into
each run's ``config.json``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from geonav.errors import ConfigError
from geonav.policy.config import A3CConfig, LossConfig, from_dict, to_dict

GRADIENT_PATHS = ("recompute", "per-step")
BASE_LOSSES = ("a3c", "ppo")
PPO_BASE_ASYNC = ("ISAR with base_loss = 'ppo' runs on the batched engine only (engine = "
                  "'batched'); the async engine implements base_loss = 'a3c'")
PPO_BASE_META = ("meta-training with ISAR's base_loss = 'ppo' is not implemented (the PPO "
                 "base exists for `train` on the batched engine); use base_loss = 'a3c'")


def check_a3c_base(cfg: Any, message: str) -> None:
    """Refuse ISAR's PPO base where it is not implemented (``message`` says where)."""
    if getattr(cfg, "base_loss", "a3c") != "a3c":
        raise ConfigError(message)


@dataclass(frozen=True)
class SAVNConfig(A3CConfig):
    """SAVN (ALGORITHMS.md (b)); ``lr`` is the outer learning rate."""

    preset: str = "savn-published"
    """'savn-published' (k=6, G=4, allenai/savn) or 'savn-aligned' (k=5, no limit); the
    preset only records which one was asked for (k_steps and inner_steps are the values)."""
    k_steps: int = 6
    """k: steps per segment; the learned loss sees exactly k rows."""
    inner_steps: int = 4
    """G: inner SGD steps per episode at most (-1: no limit)."""
    inner_lr: float = 1e-4
    """alpha: learning rate of the inner SGD steps on the policy parameters."""
    tcn_channels: int = 10
    """Channels of the learned loss's first temporal convolution (k -> 10 -> 1)."""
    second_order: bool = True
    """Differentiate the meta-loss through the inner updates (create_graph=True), as SAVN."""
    max_grad_norm: float = 0.0
    """Gradient-norm clip of the meta-gradient (0: none; SAVN does not clip it)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.k_steps < 2:
            raise ConfigError(f"k_steps must be >= 2 (the TCN needs 2 rows), got {self.k_steps}")
        if self.inner_steps < -1:
            raise ConfigError(f"inner_steps must be >= -1, got {self.inner_steps}")


SAVN_PRESETS: dict[str, dict[str, Any]] = {
    "savn-published": {"preset": "savn-published", "k_steps": 6, "inner_steps": 4},
    "savn-aligned": {"preset": "savn-aligned", "k_steps": 5, "inner_steps": -1},
}


@dataclass(frozen=True)
class ISARConfig(A3CConfig):
    """ISAR, Algorithm 1 as resolved in ALGORITHMS.md (c); ``lr`` is beta (adaptive Adam)."""

    n_steps: int = 5
    """N: steps per segment; theta takes an inner SGD step at every segment end."""
    k_segments: int = 3
    """K: segments per window; phi takes an Adam step every K*N steps."""
    alpha: float = 1e-4
    """alpha: learning rate of the inner SGD update of theta."""
    second_order: bool = True
    """Differentiate the window loss through the inner updates (Eq. 3); False gives
    sum_k grad_theta L_AC(theta_k) (first order)."""
    flush_partial_window: bool = True
    """At done, take the adaptive update on the partial window (always in the spec)."""
    gradient_path: str = "recompute"
    """'recompute': act under no_grad, then recompute each segment from its stored start
    state in one batched call with the graph; 'per-step': keep the graph of every acting
    forward (slower; the same numbers)."""
    t_max: int = 15
    """Unused by ISAR (the update schedule is n_steps and k_segments)."""
    base_loss: str = "a3c"
    """The base RL loss of every L_int and of L_adapt: 'a3c' (L_AC, ALGORITHMS.md 4.0) or
    'ppo' (PPO's clipped surrogate against the acting policy's log-probs, with the same
    GAE returns, value loss and entropy; batched engine only, docs/learning.md)."""
    clip_coef: float = 0.2
    """base_loss 'ppo': epsilon of the clipped surrogate."""
    ppo_epochs: int = 4
    """base_loss 'ppo': passes over each window's data per adaptive update, one Adam step
    each; every pass after the first recomputes the window under the new phi, inner
    updates included (the ratio leaves 1 from the second pass)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.n_steps < 1 or self.k_segments < 1:
            raise ConfigError(f"n_steps and k_segments must be >= 1, got {self.n_steps}, "
                              f"{self.k_segments}")
        if self.base_loss not in BASE_LOSSES:
            raise ConfigError(f"base_loss must be one of {BASE_LOSSES}, not {self.base_loss!r}")
        if not 0.0 < self.clip_coef < 1.0:
            raise ConfigError(f"clip_coef must lie in (0, 1), got {self.clip_coef}")
        if self.ppo_epochs < 1:
            raise ConfigError(f"ppo_epochs must be >= 1, got {self.ppo_epochs}")
        if self.gradient_path not in GRADIENT_PATHS:
            raise ConfigError(f"gradient_path must be one of {GRADIENT_PATHS}, "
                              f"not {self.gradient_path!r}")


BASE_CONFIGS: dict[str, type[A3CConfig]] = {"a3c": A3CConfig, "savn": SAVNConfig,
                                            "isar": ISARConfig}


def base_config(algo: str, options: dict[str, Any], where: str | None = None) -> A3CConfig:
    """The config of ``algo`` from a dict of options (a SAVN ``preset`` fills k and G);
    ``where`` names the table in messages (default the class name)."""
    if algo not in BASE_CONFIGS:
        raise ConfigError(f"algo must be one of {sorted(BASE_CONFIGS)}, not {algo!r}")
    opts = dict(options)
    if algo == "savn" and "preset" in opts:
        if opts["preset"] not in SAVN_PRESETS:
            raise ConfigError(f"SAVN preset must be one of {sorted(SAVN_PRESETS)}, "
                              f"not {opts['preset']!r}")
        opts = {**SAVN_PRESETS[opts["preset"]], **{k: v for k, v in opts.items()
                                                   if k != "preset"}}
    if isinstance(opts.get("loss"), LossConfig):
        opts["loss"] = to_dict(opts["loss"])
    return from_dict(BASE_CONFIGS[algo], opts, where)


@dataclass(frozen=True)
class MetaConfig:
    """Meta-training over meta-tasks, Eq. 1 (ALGORITHMS.md (d))."""

    episodes: int = 1000
    """Episodes in total, counted over all tasks (including resumed ones)."""
    workers: int = 2
    """Worker processes running the tasks of a batch in parallel (0: single process)."""
    batch_tasks: int = 0
    """B: tasks per meta update, taken in cyclic order (0: the worker count, at least 1)."""
    episodes_per_task: int = 1
    """E: episodes of the base algorithm per task visit."""
    meta_lr: float = 1e-3
    """eta: learning rate of the meta update psi <- psi - eta * sum_i g_i."""
    meta_optimizer: str = "sgd"
    """'sgd' (Eq. 1) or 'adam' (a reported option)."""
    meta_max_grad_norm: float = 0.0
    """Clip the norm of sum_i g_i before the meta update (0: off, as Eq. 1 writes; the
    unclipped sum of B tasks' episode gradients can be large enough to diverge)."""
    seed: int = 0
    """Seed of torch, numpy and the environments."""
    checkpoint_every: int = 500
    """Write checkpoints/latest.pt after the meta update that reaches every this many
    episodes (0: only the final one)."""
    torch_threads: int = 1
    """Torch intra-op threads per worker."""

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.workers < 0 or self.batch_tasks < 0 \
                or self.episodes_per_task < 1:
            raise ConfigError("episodes and episodes_per_task must be >= 1, workers and "
                              "batch_tasks >= 0")
        if self.meta_optimizer not in ("sgd", "adam"):
            raise ConfigError(f"meta_optimizer must be 'sgd' or 'adam', "
                              f"not {self.meta_optimizer!r}")
        if self.meta_lr <= 0:
            raise ConfigError(f"meta_lr must be positive, got {self.meta_lr}")

    @property
    def batch(self) -> int:
        return self.batch_tasks or max(1, self.workers)


TEACHERS = ("kl", "none", "input")
TEACHER_SCHEDULES = ("linear", "agree")
TEACHER_LOSSES = ("kl", "ce")
TEACHER_MASKS = ("none", "feasible")


@dataclass(frozen=True)
class CurriculumConfig:
    """The altitude curriculum (ALGORITHMS.md (e))."""

    levels_m: tuple[float, ...] = (75.0, 45.0, 15.0)
    """Stage altitudes in metres, in order, on the same lattice."""
    stage_episodes: int = 2000
    """Episode budget of each stage."""
    max_steps: int | None = None
    """Episode cap T_max of every stage; None: the task set's own (whole-scene tasks are
    made with the paper's 120). Set, it overrides the task set's at every level."""
    teacher: str = "kl"
    """'kl': KL prior to the previous stage's frozen policy (option A, default); 'none';
    'input': option B, the extra input slot E(o^prev) fed the view at the same cell at the
    previous stage's altitude (needs a network with NetConfig.prev_view_input; stages
    without a teacher zero-fill the slot)."""
    teacher_levels_m: tuple[float, ...] | None = None
    """Stages that get the teacher (None: every stage after the first; the paper's
    reading is (45,))."""
    teacher_decay_fraction: float = 0.25
    """lambda falls linearly from 1 to 0 over this fraction of the stage budget."""
    first_teacher_alt_m: float | None = None
    """Altitude at which the init policy (the teacher of the first stage) was trained;
    only needed when the first stage is in teacher_levels_m (e.g. 300)."""
    teacher_weight: float = 1.0
    """lambda's starting value (the paper's reading: 1)."""
    teacher_schedule: str = "agree"
    """'agree' (the default since issue 31, docs/learning.md §15) or 'linear' (the paper's
    reading, ALGORITHMS.md (e)). 'linear': lambda falls from ``teacher_weight`` to 0 over the
    first ``teacher_decay_fraction`` of the stage budget. 'agree': lambda holds at
    ``teacher_weight`` until the student's greedy action equals the teacher's on
    ``teacher_agree`` of its last 2,048 acting steps, then falls to 0 over the same span
    (batched engine only)."""
    teacher_loss: str = "kl"
    """'kl': lambda * KL(pi_T || pi_theta) (the paper's reading); 'ce': lambda times the
    cross-entropy of the teacher's greedy action under the student, on the student's own
    states (DAgger-style distillation; batched engine only)."""
    teacher_agree: float = 0.9
    """The agreement at which schedule 'agree' starts to let lambda fall."""
    teacher_mask: str = "feasible"
    """'feasible' (the default since issue 31) or 'none' (the paper's reading). 'feasible':
    the teacher's distribution is renormalised
    over the moves that are possible at the student's cell at the student's altitude (a
    move into a cell blocked there, or off the lattice, gets probability 0), so the
    higher-level policy is queried about the moves the lower level has (batched engine
    only). The mask is the trainer's knowledge of the lattice, like the collision
    penalty; the student never sees it."""

    def __post_init__(self) -> None:
        if not self.levels_m:
            raise ConfigError("levels_m must name at least one altitude")
        if self.teacher not in TEACHERS:
            raise ConfigError(f"teacher must be one of {TEACHERS}, not {self.teacher!r}")
        if self.stage_episodes < 1 or (self.max_steps is not None and self.max_steps < 1):
            raise ConfigError("stage_episodes and max_steps must be >= 1")
        if not 0.0 < self.teacher_decay_fraction <= 1.0:
            raise ConfigError("teacher_decay_fraction must lie in (0, 1]")
        if self.teacher_schedule not in TEACHER_SCHEDULES:
            raise ConfigError(f"teacher_schedule must be one of {TEACHER_SCHEDULES}, not "
                              f"{self.teacher_schedule!r}")
        if self.teacher_loss not in TEACHER_LOSSES:
            raise ConfigError(f"teacher_loss must be one of {TEACHER_LOSSES}, not "
                              f"{self.teacher_loss!r}")
        if not self.teacher_weight > 0.0:
            raise ConfigError(f"teacher_weight must be positive, got {self.teacher_weight}")
        if not 0.0 < self.teacher_agree <= 1.0:
            raise ConfigError(f"teacher_agree must lie in (0, 1], got {self.teacher_agree}")
        if self.teacher_mask not in TEACHER_MASKS:
            raise ConfigError(f"teacher_mask must be one of {TEACHER_MASKS}, not "
                              f"{self.teacher_mask!r}")
        if self.teacher != "kl" and (self.teacher_loss, self.teacher_weight,
                                     self.teacher_agree) != ("kl", 1.0, 0.9):
            raise ConfigError(f"teacher_loss, teacher_weight and teacher_agree shape the KL "
                              f"teacher's term; teacher = {self.teacher!r} has none")

    @property
    def paper_teacher_term(self) -> bool:
        """The paper's reading of the teacher's term (the async engine's only one): lambda
        1 -> 0 from the stage's start, KL, no mask. Not the default since issue 31."""
        return (self.teacher_schedule, self.teacher_loss, self.teacher_weight,
                self.teacher_mask) == ("linear", "kl", 1.0, "none")

    def teacher_at(self, stage: int) -> bool:
        if self.teacher == "none":
            return False
        if self.teacher_levels_m is None:
            return stage > 0
        return float(self.levels_m[stage]) in {float(x) for x in self.teacher_levels_m}


def kl_weight(episode: int, budget: int, fraction: float = 0.25) -> float:
    """lambda of the KL prior at a stage's ``episode`` (1-based): 1 at the first episode,
    falling linearly to 0 at ``fraction * budget`` episodes and 0 after."""
    span = fraction * budget
    if span <= 0:
        return 0.0
    return float(max(0.0, 1.0 - (episode - 1) / span))


def meta_from_dict(d: dict[str, Any]) -> MetaConfig:
    return from_dict(MetaConfig, d)


__all__ = ["SAVNConfig", "ISARConfig", "MetaConfig", "CurriculumConfig", "SAVN_PRESETS",
           "base_config", "kl_weight"]
