"""geonav.policy: encoders, the actor-critic, L_AC, the trainers, checkpoints, evaluation.

Importing this package is cheap; the submodules import torch. Main entry points:

* **training**: :func:`geonav.policy.engine.build_trainer` (``build_trainer(algo, engine,
  env_factory, net_cfg, cfg)``, then ``.train()``): A3C, SAVN, ISAR and **PPO**
  (:class:`geonav.policy.batched.ppo.PPOConfig`) on the default **batched** engine
  (:mod:`geonav.policy.batched`: many episodes in lock-step in one process), or the
  paper-faithful async reference (``engine="async"``: :class:`~geonav.policy.a3c.A3CTrainer`,
  :class:`~geonav.policy.savn.SAVNTrainer`, :class:`~geonav.policy.isar.ISARTrainer`);
  :func:`geonav.policy.engine.build_meta_trainer` for meta-training (Eq. 1) and
  :func:`geonav.policy.curriculum.run_curriculum` for the altitude curriculum; configs
  :class:`geonav.policy.config.NetConfig`, :class:`~geonav.policy.config.A3CConfig` and
  :mod:`geonav.policy.meta_config`; progress and metrics through
  :class:`geonav.policy.callbacks.Callback`;
* **evaluation**: :func:`geonav.policy.evaluation.evaluate_checkpoint` (a checkpoint on a
  scene's task set, greedy, sampled and view-ablated, beside chance: ``geonav eval``) and
  :func:`geonav.policy.evaluation.evaluate` (a live model);
* :func:`geonav.policy.checkpoint.load_checkpoint` and ``save_checkpoint``
  (``weights_only`` loads);
* :class:`geonav.policy.inference.PolicyRunner` (deployment);
* :class:`geonav.policy.model.ActorCritic` and :func:`geonav.policy.losses.actor_critic_loss`
  (the segment loss L_AC).

With Stable-Baselines3 instead: ``gymnasium.make("geonav/GeoNav-v0", ...)`` with
:mod:`geonav.wrappers` (docs/guide.md §4).
"""

from __future__ import annotations

from typing import Any

_EXPORTS = {
    "ActorCritic": "geonav.policy.model",
    "NetConfig": "geonav.policy.config",
    "A3CConfig": "geonav.policy.config",
    "LossConfig": "geonav.policy.config",
    "actor_critic_loss": "geonav.policy.losses",
    "A3CTrainer": "geonav.policy.a3c",
    "train_a3c": "geonav.policy.a3c",
    "load_checkpoint": "geonav.policy.checkpoint",
    "save_checkpoint": "geonav.policy.checkpoint",
    "evaluate": "geonav.policy.evaluation",
    "PolicyRunner": "geonav.policy.inference",
    "ISARTrainer": "geonav.policy.isar",
    "SAVNTrainer": "geonav.policy.savn",
    "MetaTrainer": "geonav.policy.meta",
    "run_curriculum": "geonav.policy.curriculum",
    "build_trainer": "geonav.policy.engine",
    "build_meta_trainer": "geonav.policy.engine",
    "evaluate_checkpoint": "geonav.policy.evaluation",
    "PPOConfig": "geonav.policy.batched.ppo",
    "Callback": "geonav.policy.callbacks",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'geonav.policy' has no attribute {name!r}")
