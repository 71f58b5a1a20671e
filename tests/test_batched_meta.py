"""Batched meta-training: the reference MetaTrainer's meta update, learning, resume."""

import functools
import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from batched_helpers import greedy_sr, random_sr
from test_meta_training import multi_task_factory

from geonav.env import GeoNavEnv
from geonav.policy import a3c as a3c_mod
from geonav.policy import encoders
from geonav.policy import isar as isar_mod
from geonav.policy import savn as savn_mod
from geonav.policy.batched import meta as meta_mod
from geonav.policy.batched import savn as batched_savn_mod
from geonav.policy.batched.meta import BatchedMetaSAVN
from geonav.policy.callbacks import Callback, read_metrics
from geonav.policy.checkpoint import load_checkpoint
from geonav.policy.config import A3CConfig
from geonav.policy.engine import build_meta_trainer
from geonav.policy.meta import MetaTrainer, TaskRunner
from geonav.policy.meta_config import ISARConfig, MetaConfig, SAVNConfig
from geonav.policy.testing import tiny_env_factory, tiny_net


@pytest.mark.parametrize("encoder", ["random", "cnn"])
def test_first_meta_update_equals_reference(tmp_path, encoder):
    """SAVN base (the trainable CNN adapted per slot in the inner steps, too)."""
    factory = tiny_env_factory(cells=5, max_steps=12)
    net = tiny_net(encoder, 32, size=16)
    base = SAVNConfig(k_steps=3, inner_steps=2, inner_lr=0.5)
    meta = MetaConfig(episodes=1, workers=0, batch_tasks=1, meta_lr=0.1, seed=4)
    ref = MetaTrainer(factory, net, "savn", base, meta, tensorboard=False)
    ref.train()
    bat = build_meta_trainer("savn", "batched", factory, net, base, meta, out_dir=tmp_path,
                             tensorboard=False)
    assert isinstance(bat, BatchedMetaSAVN)
    res = bat.train()
    assert res.episodes == 1 and bat.meta_updates == 1
    for (n, a), b in zip(ref.model.named_parameters(), bat.model.parameters(), strict=True):
        torch.testing.assert_close(b.detach(), a.detach(), atol=1e-6, rtol=1e-5, msg=n)
    for a, b in zip(ref.aux["interaction_loss"].parameters(),
                    bat.aux["interaction_loss"].parameters(), strict=True):
        torch.testing.assert_close(b.detach(), a.detach(), atol=1e-6, rtol=1e-5)
    cfg = (tmp_path / "config.json").read_text()
    assert '"meta-savn"' in cfg and '"meta_lr": 0.1' in cfg


def test_slots_run_the_batch_tasks_in_cyclic_order():
    u = tiny_env_factory(cells=4, max_steps=6)().unwrapped
    tasks = [u.tasks[0], replace(u.tasks[0], name="tiny-b", target_cell=(0, 0))]
    two = functools.partial(GeoNavEnv, u.scene, tasks, camera=u.camera)
    bat = BatchedMetaSAVN(two, tiny_net("random", 32, size=16), SAVNConfig(k_steps=3),
                          MetaConfig(episodes=9, batch_tasks=3, workers=0),
                          tensorboard=False)
    res = bat.train()
    assert [r["task_index"] for r in res.records[:3]] == [0, 1, 0]
    assert sorted(r["task_index"] for r in res.records[3:6]) == [0, 1, 1]
    assert bat.meta_updates == 3


# -- ISAR and A3C bases: per-task parameters ------------------------------------------------

L = 12  # max_steps of the meta-tasks below


@pytest.fixture
def float64(monkeypatch):
    """Everything in float64, the frozen encoder's input included."""
    old = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    to_float = encoders.images_to_float
    monkeypatch.setattr(encoders, "images_to_float",
                        lambda *a, **k: to_float(*a, **k).to(torch.float64))
    yield
    torch.set_default_dtype(old)


def force_actions(monkeypatch, script):
    """The same actions in both engines: ``script[task][t]`` at step t of an episode."""
    now = {"task": 0, "t": 0}
    run = TaskRunner.run

    def ref_run(self, psi, task_index, first_episode, episodes):
        now.update(task=task_index, t=0)
        return run(self, psi, task_index, first_episode, episodes)

    def ref_choose(logits, greedy, rng):
        now["t"] += 1
        return int(script[now["task"]][now["t"] - 1])

    reset_env = a3c_mod.A3CWorker.reset_env

    def ref_reset(self):  # every episode of a task visit follows the task's script
        now["t"] = 0
        return reset_env(self)

    monkeypatch.setattr(TaskRunner, "run", ref_run)
    monkeypatch.setattr(a3c_mod.A3CWorker, "reset_env", ref_reset)
    monkeypatch.setattr(isar_mod, "choose_action", ref_choose)
    monkeypatch.setattr(a3c_mod, "choose_action", ref_choose)
    box = {}

    def bat_sample(logits, rng, live=None):
        v = box["trainer"].venv
        return torch.tensor([int(script[v.task[s]][min(v.steps[s], L - 1)])
                             for s in range(v.n_slots)])

    monkeypatch.setattr(meta_mod, "sample_actions", bat_sample)
    monkeypatch.setattr(savn_mod, "choose_action", ref_choose)
    monkeypatch.setattr(batched_savn_mod, "sample_actions", bat_sample)
    return box


BASES = {"isar2": ISARConfig(n_steps=2, k_segments=3, alpha=0.5, lr=0.05, max_grad_norm=0.2),
         "isar1": ISARConfig(n_steps=2, k_segments=3, alpha=0.5, lr=0.05, max_grad_norm=0.2,
                             second_order=False),
         "a3c": A3CConfig(t_max=3, lr=0.05, max_grad_norm=0.2),
         "savn": SAVNConfig(k_steps=3, inner_steps=2, inner_lr=0.5, lr=0.05,
                            max_grad_norm=0.2)}


@pytest.mark.parametrize("base", [*(k for k in BASES if k != "savn"), "isar2-prev", "isar2-E2",
                                  "a3c-E2", "isar2-steps", "a3c-steps", "savn-E2",
                                  "savn-E2-cnn", "isar2-cnn", "isar1-cnn", "a3c-cnn",
                                  "isar2-E2-cnn", "a3c-E2-cnn", "isar2-noflush",
                                  "isar1-E2-noflush", "isar2-noflush-cnn", "isar2-warm",
                                  "isar2-E2-warm", "a3c-E2-warm", "savn-E2-warm",
                                  "isar2-E2-warm-cnn"])
@pytest.mark.parametrize("b", [1, 3])
def test_meta_update_equals_reference(float64, monkeypatch, base, b):
    """B tasks' gradients g_i and the meta update equal the async MetaTrainer's (its
    TaskRunner's, one task after another) on the same trajectories, to 1e-10 (isar2-prev:
    a network with the zero-filled previous-altitude input slot; -E2: E = 2 episodes per
    task visit, the second going on from the first's phi^i and in-task Adam; -steps: the
    view embeddings evaluated per step, not as a table per window; -cnn: the trainable
    CNN, per-task copies of it; savn: the learned loss's gradients too; -noflush:
    flush_partial_window = false with windows of 4 segments of 2 steps, so task 1's
    episode (6 steps) and the 12-step ones end in partial windows, which are dropped;
    -warm: lr_warmup = 3, each task's in-task Adam ramping from its own step count)."""
    encoder = "cnn" if base.endswith("-cnn") else "random"
    base = base.removesuffix("-cnn")
    noflush, warm = base.endswith("-noflush"), base.endswith("-warm")
    base = base.removesuffix("-noflush").removesuffix("-warm")
    e = 2 if base.endswith("-E2") else 1
    if base.endswith("-steps"):
        monkeypatch.setattr(meta_mod, "PRE_TABLE_VIEWS_PER_STEP", 0)
    base = base.removesuffix("-E2").removesuffix("-steps")
    base, prev = base.removesuffix("-prev"), base.endswith("-prev")
    algo = base[:4].rstrip("12")
    # the CNN at the in-task lr 0.05 reaches gradients of 1e4 in a visit's second episode,
    # where 1e-10 is below float64's summation-order noise: 0.01 keeps them near 1
    cfg = replace(BASES[base], lr=0.01) if encoder == "cnn" else BASES[base]
    if noflush:
        cfg = replace(cfg, flush_partial_window=False, k_segments=4)
    if warm:
        cfg = replace(cfg, lr_warmup=3)
    factory = multi_task_factory(3)
    script = np.random.default_rng(5).integers(0, 4, (3, L))
    script[1, :6] = [3, 2, 3, 2, 3, 2]  # task 1 walks to its target (0, 0)
    box = force_actions(monkeypatch, script)
    net = replace(tiny_net(encoder, 32, size=16), prev_view_input=prev)
    meta = MetaConfig(episodes=2 * b * e, workers=0, batch_tasks=b, meta_lr=0.1, seed=4,
                      episodes_per_task=e)
    ref = MetaTrainer(factory, net, algo, cfg, meta, keep_task_grads=True,
                      tensorboard=False)
    ref_res = ref.train()
    bat = build_meta_trainer(algo, "batched", factory, net, cfg, meta,
                             keep_task_grads=True, tensorboard=False)
    box["trainer"] = bat
    assert type(bat).__name__ == {"isar": "BatchedMetaISAR", "a3c": "BatchedMetaA3C",
                                  "savn": "BatchedMetaSAVN"}[algo]
    res = bat.train()
    lengths = [r["length"] for r in res.records]
    assert lengths == [r["length"] for r in ref_res.records]
    assert [r["success"] for r in res.records] == [r["success"] for r in ref_res.records]
    for key in ("inner_updates", "adaptive_updates", "meta_update", "task_index"):
        assert [r.get(key) for r in res.records] == [r.get(key) for r in ref_res.records]
    if b == 3:  # one episode ends early, mid-window; the others run to the cap
        assert lengths[e] < L and L in lengths, lengths
    if e == 2:  # a visit's second episode starts where the first left phi^i and its Adam
        assert [r["task_index"] for r in res.records[:2 * b]] == \
            [j for j in range(b) for _ in range(2)]
    names = [n for n, _ in ref.model.named_parameters()] + \
        [f"tcn.{n}" for m in ref.aux.values() for n, _ in m.named_parameters()]
    assert len(bat.update_log) == len(ref.update_log) == 2  # the second reuses the buffers
    if noflush:  # some episodes end in a partial window (windows of 8 steps)
        assert any(r["adaptive_updates"] < -(-r["length"] // 8) for r in ref_res.records)
    for u, (r_log, b_log) in enumerate(zip(ref.update_log, bat.update_log, strict=True)):
        assert b_log["tasks"] == r_log["tasks"]
        for i in range(b):
            visit = ref_res.records[u * b * e:(u + 1) * b * e][i * e:(i + 1) * e]
            for n, x, y in zip(names, r_log["grads"][i], b_log["grads"][i], strict=True):
                if not any(r.get("adaptive_updates", 1) for r in visit):  # all windows partial
                    assert float(x.abs().max()) == 0, n
                else:
                    assert float(x.abs().max()) > 0 or n.startswith("prev_embed"), n  # 0 input
                torch.testing.assert_close(y, x, atol=1e-10, rtol=1e-10, msg=f"task {i} {n}")
        for n, x, y in zip(names, r_log["psi_after"], b_log["psi_after"], strict=True):
            torch.testing.assert_close(y, x, atol=1e-10, rtol=1e-10, msg=n)


def corner_tasks(max_steps=7):
    """Four meta-tasks on the tiny 4 x 4 lattice, targets at its corners; with 7 steps
    the uniformly random walk succeeds from 15 % of the starts."""
    return multi_task_factory(4, max_steps=max_steps)


@pytest.mark.parametrize("case", ["isar", "a3c", "savn-E2", "isar-cnn", "a3c-cnn"])
def test_learns_tiny_meta_task_set(case):
    """Greedy success over every start of every meta-task, far beyond random (meta Adam,
    as the SAVN row's; with Eq. 1's SGD at eta 1e-2 this budget is too small). savn-E2:
    E = 2 episodes per task visit on per-task parameters; -cnn: the trainable CNN."""
    algo, e = case.split("-")[0], 2 if "-E2" in case else 1
    encoder = "cnn" if case.endswith("-cnn") else "random"
    factory = corner_tasks()
    env = factory()
    kw = {"lr": 1e-3, "adam_eps": 1e-5, "amsgrad": False, "eval_every": 0}
    base = {"isar": lambda: ISARConfig(alpha=1e-2, second_order=False, **kw),
            "a3c": lambda: A3CConfig(**kw), "savn": lambda: SAVNConfig(**kw)}[algo]()
    meta = MetaConfig(episodes=2000, batch_tasks=16, meta_optimizer="adam", meta_lr=1e-3,
                      seed=1, episodes_per_task=e)
    t = build_meta_trainer(algo, "batched", factory, tiny_net(encoder, 32), base, meta,
                           tensorboard=False)
    assert t.engine_choice.engine == "batched"
    res = t.train()
    assert t.meta_updates == -(-2000 // (16 * e)) and res.episodes == 2000
    sr, rnd = greedy_sr(res.model, t.frozen, env), random_sr(env)
    assert rnd < 0.2 and sr >= rnd + 0.5, (sr, rnd)


class Kill(Callback):
    """Dies at an episode, as a killed process would (after a checkpoint)."""

    def __init__(self, at):
        self.at = at

    def on_episode(self, record):
        if record["episode"] == self.at:
            raise KeyboardInterrupt


def test_kill_and_resume_continues(tmp_path):
    """Killed after the checkpoint of episode 6, resumed from it: the cyclic task order,
    the meta updates and the parameters go on as in a run that was never interrupted."""
    factory = multi_task_factory(3)
    net = tiny_net("random", 32, size=16)
    base = ISARConfig(n_steps=2, k_segments=3, alpha=0.1, lr=1e-2, eval_every=0)
    meta = MetaConfig(episodes=12, batch_tasks=3, meta_lr=0.1, checkpoint_every=6, seed=2)
    whole = build_meta_trainer("isar", "batched", factory, net, base, meta, tensorboard=False)
    full = whole.train()
    run = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        build_meta_trainer("isar", "batched", factory, net, base, meta, out_dir=run,
                           callbacks=[Kill(8)], tensorboard=False).train()
    assert len(read_metrics(run / "metrics.csv")) == 8
    latest = run / "checkpoints" / "latest.pt"
    ck = load_checkpoint(latest)
    assert ck.episodes == 6 and ck.meta["meta_updates"] == 2
    assert ck.meta["config"]["base_algorithm"] == "isar"
    t = build_meta_trainer("isar", "batched", factory, None, base, meta, out_dir=run,
                           resume=latest, keep_task_grads=False, tensorboard=False)
    res = t.train()
    assert [r["task_index"] for r in res.records] == [0, 1, 2, 0, 1, 2]
    assert [u["tasks"] for u in t.update_log] == [[0, 1, 2], [0, 1, 2]]
    assert t.meta_updates == 4 and res.episodes == 12
    rows = read_metrics(run / "metrics.csv")
    assert [r["episode"] for r in rows] == list(range(1, 13))
    assert {"inner_updates", "adaptive_updates"} <= set(full.records[0])
    for (n, a), b in zip(whole.model.named_parameters(), t.model.parameters(), strict=True):
        torch.testing.assert_close(b, a, atol=1e-6, rtol=1e-6, msg=n)
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["algorithm"] == "meta-isar" and cfg["engine"]["name"] == "batched"


@pytest.mark.parametrize("product", ["SlotProduct", "SharedProduct"])
def test_recorded_products_do_not_keep_the_window_alive(product):
    """An inner step with the graph records its backward products in the recorder; once
    the window's objects are dropped, reference counting alone must free the recorder
    and its graph. (A strong recorder reference on the autograd node closed a cycle
    through torch's C++ graph that no collector sees: meta-training grew by about
    290 MiB per 1,000 episodes, bench/bench_meta_memory.py.)"""
    import gc
    import weakref

    from geonav.policy.batched import core

    fn = getattr(core, product)
    b, n_in, n_out = 3, 4, 5
    w = torch.randn(b, n_in, n_out) if product == "SlotProduct" else torch.randn(n_out, n_in)
    x = torch.randn(b, n_in, requires_grad=True)
    rec = core.Recorder()
    y = fn.apply(x, w, "fc", rec)
    (gx,) = torch.autograd.grad(y.square().sum(), x, create_graph=True)
    assert len(rec.back) == 1 and rec.back[0][1].requires_grad  # the 2nd-order path
    alive = weakref.ref(rec)
    gc.disable()  # reference counting only: the collector must not be needed
    try:
        del rec, y, gx
        assert alive() is None
    finally:
        gc.enable()
