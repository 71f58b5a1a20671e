"""Helpers of the batched-engine tests: greedy success over every start cell."""

import numpy as np
import torch

from geonav.policy.evaluation import RandomAgent, evaluate


def float64(trainer):
    """The trainer's network (and SAVN's learned loss) and Adam in float64 (the frozen
    encoder stays float32; its feature table is cast to the network's dtype)."""
    trainer.model.double()
    trainer.params_list = list(trainer.model.parameters())
    for m in getattr(trainer, "aux", {}).values():
        m.double()
        trainer.params_list += list(m.parameters())
    trainer.optimizer = trainer.build_optimizer(trainer.params_list)
    return trainer


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


def first_update_grads(ref, bat):
    """The gradients of the first update of a reference trainer's inline worker (its
    first episode) and of a batched trainer (its first update), and that episode's record."""
    worker = ref.inline_worker()
    ref_grads, got = [], []
    worker.on_gradients = lambda gs: ref_grads.append([g.clone() for g in gs])
    worker.events = []
    rec = worker.run_episode(1)
    bat._setup()
    bat.on_gradients = lambda gs: got.append([g.clone() for g in gs])
    finals, _ = bat.update()
    return ref_grads[0], got[0], rec, worker, finals


def assert_grads_close(names, ref, got, atol, rtol):
    assert len(got) == len(ref) == len(names)
    for n, a, b in zip(names, ref, got, strict=True):
        torch.testing.assert_close(b, a, atol=atol, rtol=rtol, msg=n)


def kl_teacher_spec(net, out_dir, budget=40):
    """A curriculum KL teacher: a tiny A3C policy trained at 90 m on the tiny lattice."""
    from geonav.policy.a3c import A3CTrainer
    from geonav.policy.config import A3CConfig
    from geonav.policy.teacher import TeacherSpec
    from geonav.policy.testing import tiny_env_factory

    at_90 = tiny_env_factory(cells=5, max_steps=12, alt_m=90.0)
    run = A3CTrainer(at_90, net, A3CConfig(episodes=3, workers=0, seed=1), out_dir=out_dir,
                     tensorboard=False).train()
    return TeacherSpec(str(run.checkpoint), at_90, budget=budget)

