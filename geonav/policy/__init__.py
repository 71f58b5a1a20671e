"""geonav.policy: encoders, the actor-critic, L_AC, the A3C trainer, checkpoints, evaluation.

Importing this package is cheap; the submodules import torch. Main entry points:

* :class:`geonav.policy.model.ActorCritic` and :class:`geonav.policy.config.NetConfig`;
* :func:`geonav.policy.losses.actor_critic_loss` (the segment loss L_AC);
* :class:`geonav.policy.a3c.A3CTrainer` / :func:`geonav.policy.a3c.train_a3c`;
* :func:`geonav.policy.checkpoint.load_checkpoint` and ``save_checkpoint``;
* :func:`geonav.policy.evaluation.evaluate`;
* :class:`geonav.policy.inference.PolicyRunner` (deployment);
* :class:`geonav.policy.isar.ISARTrainer`, :class:`geonav.policy.savn.SAVNTrainer`,
  :class:`geonav.policy.meta.MetaTrainer` and :func:`geonav.policy.curriculum.run_curriculum`.
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
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'geonav.policy' has no attribute {name!r}")
