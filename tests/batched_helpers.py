"""Helpers of the batched-engine tests: greedy success over every start cell."""

import numpy as np

from geonav.policy.evaluation import RandomAgent, evaluate


def all_starts(env):
    u = env.unwrapped
    return [(ti, c) for ti in range(len(u.tasks)) for c in u.start_cells(ti)]


def greedy_sr(model, frozen, env):
    """Greedy success rate of a policy from every valid start of every task."""
    return evaluate(model.cpu(), env, frozen=frozen, starts=all_starts(env)).success_rate


def random_sr(env, seeds=5):
    """The uniformly random agent's success rate from every start, averaged over seeds."""
    return float(np.mean([evaluate(RandomAgent(seed=s), env, starts=all_starts(env),
                                   seed=s).success_rate for s in range(seeds)]))
