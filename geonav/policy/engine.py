"""Which trainer runs an algorithm: the batched engine (default) or the async reference.

``engine = "batched"`` (:mod:`geonav.policy.batched`) steps many episodes in lock-step in
one process; ``engine = "async"`` is the per-episode, multi-process trainer of
:mod:`geonav.policy.a3c` (with :mod:`~geonav.policy.savn` and :mod:`~geonav.policy.isar`),
the paper-faithful asynchronous form and the reference the batched learners are tested
against. Both write the same run folders, checkpoints and metrics.

The batched engine implements every combination the async one does (the last gaps,
ISAR's ``flush_partial_window = false`` and the previous-altitude view input of A3C, are
closed), so :func:`resolve` (and :func:`build_meta_trainer`) no longer falls back;
:func:`_fallback_reason` stays the one place a future gap would be named: the trainers
would log it as a warning and record it in config.json.
PPO, ISAR with ``base_loss = "ppo"`` and the previous-altitude view input of A3C exist
on the batched engine only.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

from geonav.errors import ConfigError

log = logging.getLogger(__name__)

ENGINES = ("batched", "async")
ALGOS = ("a3c", "savn", "isar", "ppo")


@dataclass(frozen=True)
class EngineChoice:
    """The trainer class chosen for an algorithm, and why."""

    cls: type
    engine: str
    """'batched' or 'async' (what actually runs)."""
    reason: str | None = None
    """Why the batched engine was not used, when it was asked for."""


def _fallback_reason(algo: str, net_cfg: Any, cfg: Any, teacher: bool, prev_view: bool
                     ) -> str | None:
    """Why the batched engine cannot run this combination, or None (it runs them all)."""
    return None


def resolve(algo: str, engine: str = "batched", net_cfg: Any = None, cfg: Any = None, *,
            teacher: bool = False, prev_view: bool = False) -> EngineChoice:
    """The trainer class for ``algo`` on ``engine`` (see the module docstring).

    ``net_cfg`` None means the trainers' default network (the trainable CNN).
    """
    if engine not in ENGINES:
        raise ConfigError(f"engine must be one of {ENGINES}, not {engine!r}")
    if algo not in ALGOS:
        raise ConfigError(f"algo must be one of {ALGOS}, not {algo!r}")
    ppo_base = algo == "isar" and getattr(cfg, "base_loss", "a3c") == "ppo"
    if engine == "batched":
        reason = _fallback_reason(algo, net_cfg, cfg, teacher, prev_view)
        if reason is not None and ppo_base:
            raise ConfigError(f"ISAR with base_loss = 'ppo' runs on the batched engine only, "
                              f"and {reason}")
        if reason is None:
            from geonav.policy.batched.isar import BatchedISARTrainer
            from geonav.policy.batched.ppo import BatchedPPOTrainer
            from geonav.policy.batched.savn import BatchedSAVNTrainer
            from geonav.policy.batched.trainer import BatchedA3CTrainer

            cls = {"a3c": BatchedA3CTrainer, "isar": BatchedISARTrainer,
                   "savn": BatchedSAVNTrainer, "ppo": BatchedPPOTrainer}[algo]
            return EngineChoice(cls, "batched")
        if algo == "ppo":
            raise ConfigError(f"PPO runs on the batched engine only, and {reason}")
        log.warning("engine 'batched': %s; running %s on engine 'async'", reason, algo)
    elif algo == "ppo":
        raise ConfigError("PPO exists on the batched engine only; use engine = 'batched'")
    elif ppo_base:
        from geonav.policy.meta_config import PPO_BASE_ASYNC

        raise ConfigError(PPO_BASE_ASYNC)
    elif prev_view and algo == "a3c":
        raise ConfigError("the previous-altitude view input (curriculum teacher = 'input') "
                          "for a3c runs on the batched engine only (the async A3C worker "
                          "has no extra input); use engine = 'batched', or isar or savn")
    else:
        reason = None
    from geonav.policy.a3c import A3CTrainer
    from geonav.policy.isar import ISARTrainer
    from geonav.policy.savn import SAVNTrainer

    return EngineChoice({"a3c": A3CTrainer, "isar": ISARTrainer, "savn": SAVNTrainer}[algo],
                        "async", reason)


def build_trainer(algo: str, engine: str, env_factory: Any, net_cfg: Any, cfg: Any, *,
                  batch: int | None = None, device: str | None = None,
                  **kwargs: Any) -> Any:
    """Construct the trainer :func:`resolve` picks; ``batch`` and ``device`` go to the
    batched engine (the async one runs on the CPU and refuses another device)."""
    choice = resolve(algo, engine, net_cfg, cfg, teacher=kwargs.get("teacher") is not None,
                     prev_view=kwargs.get("prev_view") is not None)
    if choice.engine == "batched":
        from geonav.policy.batched.trainer import DEFAULT_BATCH

        trainer = choice.cls(env_factory, net_cfg, cfg, batch=batch or DEFAULT_BATCH,
                             device=device or "cpu", **kwargs)
    else:
        if device not in (None, "cpu"):
            raise ConfigError(f"the async engine runs on the CPU; device {device!r} needs "
                              "engine = 'batched'")
        trainer = choice.cls(env_factory, net_cfg, cfg, **kwargs)
        base = trainer.resolved_config  # the async trainers record the engine through this
        trainer.resolved_config = lambda: {**base(), "engine": {
            "name": "async", "asked": engine, "fallback_reason": choice.reason}}
    trainer.engine_choice = choice
    return trainer


def build_meta_trainer(algo: str, engine: str, env_factory: Any, net_cfg: Any, base_cfg: Any,
                       meta_cfg: Any, *, batch: int | None = None, device: str | None = None,
                       **kwargs: Any) -> Any:
    """Meta-training on the batched engine where it is implemented (SAVN, ISAR and A3C
    bases, any E, frozen encoder or trainable CNN, ``flush_partial_window`` and
    ``lr_warmup``: :mod:`geonav.policy.batched.meta`), else
    :class:`~geonav.policy.meta.MetaTrainer` (async, with a warning when the batched engine
    was asked for). ``batch`` is unused: B is the meta-batch."""
    if engine not in ENGINES:
        raise ConfigError(f"engine must be one of {ENGINES}, not {engine!r}")
    if algo not in ("a3c", "savn", "isar"):
        raise ConfigError(f"meta-training base must be one of a3c, isar, savn, not {algo!r}")
    from geonav.policy.meta_config import PPO_BASE_META, check_a3c_base

    check_a3c_base(base_cfg, PPO_BASE_META)
    reason = None
    if engine == "batched":
        if net_cfg is None and kwargs.get("resume") is not None:
            from geonav.policy.checkpoint import load_checkpoint

            net_cfg = load_checkpoint(kwargs["resume"]).net_config  # the resumed network
        reason = _fallback_reason(algo, net_cfg, base_cfg, False, False)
        if reason is None:
            from geonav.policy.batched.meta import BATCHED_META

            cls = BATCHED_META[algo]
            trainer: Any = cls(env_factory, net_cfg, base_cfg, meta_cfg,
                               device=device or "cpu", **kwargs)
            trainer.engine_choice = EngineChoice(cls, "batched")
            return trainer
        log.warning("engine 'batched': %s; meta-training on engine 'async'", reason)
    if device not in (None, "cpu"):
        raise ConfigError(f"meta-training on the async engine runs on the CPU; device "
                          f"{device!r} needs the batched engine")
    from geonav.policy.meta import MetaTrainer

    trainer = MetaTrainer(env_factory, net_cfg, algo, base_cfg, meta_cfg, **kwargs)
    base = trainer.resolved_config
    trainer.resolved_config = lambda: {**base(), "engine": {
        "name": "async", "asked": engine, "fallback_reason": reason}}
    trainer.engine_choice = EngineChoice(MetaTrainer, "async", reason)
    return trainer


__all__ = ["ENGINES", "EngineChoice", "resolve", "build_trainer", "build_meta_trainer"]
