"""The batched training engine: B episodes in lock-step in one process.

* :mod:`geonav.policy.batched.core`: the batched forward of ActorCritic from its
  parameters, with exact factored per-slot adapted weights;
* :mod:`geonav.policy.batched.trainer`: the engine's trainer machinery and synchronous
  A3C; :mod:`geonav.policy.batched.ppo`: PPO; :mod:`geonav.policy.batched.isar`: ISAR.

The vectorised environment is :class:`geonav.vecenv.LatticeVecEnv`. The per-episode,
multi-process trainers (:mod:`geonav.policy.a3c` and the rest) stay as
``engine = "async"``, the reference these are tested against.
"""
