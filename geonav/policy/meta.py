"""Meta-training over meta-tasks, Eq. 1 (ALGORITHMS.md (d)).

Each meta-iteration takes the next B tasks in cyclic order. For each task i:
phi^i <- psi; run E episodes of the base algorithm (A3C, SAVN or ISAR) on task i
with a *fresh* Adam (lr = the base config's ``lr``) for its in-task updates; the task
gradient g_i is the sum of every gradient the base algorithm hands to its optimiser
(unclipped): for SAVN the exact meta-gradient w.r.t. its initial parameters (= psi,
with E = 1); for ISAR the sum over windows of grad_phi_hat L_adapt at the current
phi^i (first order in psi: d phi^i / d psi is taken as I, the in-task Adam steps are
not differentiated); for A3C the sum of its rollout gradients. Then
psi <- psi - eta * sum_i g_i (SGD; Adam optional). Later visits restart from the new
psi. Episodes are counted over all tasks.

With ``workers > 0`` the B tasks of a batch run in parallel processes (task j of the
batch on worker j mod W); each writes g_i into its own shared-memory buffer.
"""

from __future__ import annotations

import copy
import queue as queue_mod
import traceback
from collections.abc import Sequence
from typing import Any

import torch
from torch import nn

from geonav.errors import ConfigError
from geonav.policy.a3c import A3CTrainer, A3CWorker, TrainResult, WorkerFailed
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig, NetConfig, to_dict
from geonav.policy.encoders import build_frozen_encoder
from geonav.policy.isar import ISARWorker, gradient_path
from geonav.policy.meta_config import PPO_BASE_META, MetaConfig, check_a3c_base
from geonav.policy.model import ActorCritic
from geonav.policy.savn import InteractionLoss, SAVNWorker

WORKERS: dict[str, type[A3CWorker]] = {"a3c": A3CWorker, "savn": SAVNWorker,
                                       "isar": ISARWorker}


TASK_GRADIENT = {"isar": "first order in psi: sum over windows of grad_phi_hat L_adapt at "
                         "the current phi^i",
                 "savn": "exact meta-gradient w.r.t. the initial parameters",
                 "a3c": "sum of the rollout gradients at the current phi^i"}
"""What config.json records as the task gradient g_i of each base algorithm."""


def meta_step(optimizer: torch.optim.Optimizer, psi: list[torch.Tensor],
              grads: list[list[torch.Tensor]], max_norm: float = 0.0, *,
              keep: bool = False, total: list[torch.Tensor] | None = None) -> dict[str, Any]:
    """psi <- psi - eta * sum_i g_i with the meta optimiser (``max_norm`` > 0 clips the
    sum first); returns the update's log entry (with ``keep``: psi before and after and
    the task gradients). ``total``: the sum, when the caller has it (consumed)."""
    if total is None:
        total = [torch.zeros_like(p) for p in psi]
        for task in grads:
            torch._foreach_add_(total, task)
    entry: dict[str, Any] = {}
    if keep:
        entry["psi_before"] = [p.detach().clone() for p in psi]
        entry["grads"] = [[x.clone() for x in g] for g in grads]
    if max_norm > 0:
        norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g)
                                                     for g in total]))
        entry["grad_norm"] = float(norm)
        scale = max_norm / (float(norm) + 1e-6)
        if scale < 1.0:
            torch._foreach_mul_(total, scale)
    for p, g in zip(psi, total, strict=True):
        p.grad = g
    optimizer.step()
    optimizer.zero_grad(set_to_none=True)
    if keep:
        entry["psi_after"] = [p.detach().clone() for p in psi]
    return entry


def checkpoint_after_update(trainer: Any, before: int, cbs: list[Callback], rng: Any) -> None:
    """checkpoints/latest.pt after the meta update that reaches a multiple of the meta
    config's ``checkpoint_every`` episodes (``before``: the episodes before the update),
    so a resume starts at a batch boundary and goes on with the cyclic task order."""
    every = trainer.meta_cfg.checkpoint_every
    if trainer.out_dir is not None and every and \
            trainer.episodes_done // every > before // every:
        path = trainer.save(trainer.out_dir / "checkpoints" / "latest.pt",
                            trainer.episodes_done, rng())
        for cb in cbs:
            cb.on_checkpoint(path, trainer.episodes_done)


class TaskRunner:
    """Runs the base algorithm on one task from psi and returns (records, g_i)."""

    def __init__(self, algo: str, env: Any, net_cfg: NetConfig, cfg: A3CConfig, seed: int,
                 aux: dict[str, nn.Module]) -> None:
        self.algo = algo
        self.cfg = cfg
        self.model = ActorCritic(net_cfg)
        self.aux = {k: copy.deepcopy(m) for k, m in aux.items()}
        frozen = build_frozen_encoder(net_cfg)
        kwargs: dict[str, Any] = {}
        if algo == "savn":
            kwargs["tcn"] = self.aux["interaction_loss"]
        self.worker = WORKERS[algo](0, self.model, None, env, cfg, frozen,  # type: ignore[arg-type]
                                    seed, **kwargs)
        if hasattr(self.worker, "attach"):
            self.worker.attach(None)
        self.params = self.worker._params

    def run(self, psi: Sequence[torch.Tensor], task_index: int, first_episode: int,
            episodes: int) -> tuple[list[dict[str, Any]], list[torch.Tensor]]:
        """phi^i <- psi, E episodes on ``task_index`` with a fresh Adam; (records, g_i)."""
        cfg = self.cfg
        with torch.no_grad():
            torch._foreach_copy_(self.params, list(psi))
        self.worker.optimizer = torch.optim.Adam(
            self.params, lr=cfg.lr, betas=cfg.adam_betas, eps=cfg.adam_eps,
            amsgrad=cfg.amsgrad, fused=cfg.fused or None)
        acc = [torch.zeros_like(p) for p in self.params]

        def add(grads: list[torch.Tensor]) -> None:
            torch._foreach_add_(acc, [g if g is not None else torch.zeros_like(a)
                                      for a, g in zip(acc, grads, strict=True)])

        self.worker.on_gradients = add
        self.worker.reset_options = {"task": int(task_index)}
        recs = []
        for e in range(episodes):
            rec = self.worker.run_episode(first_episode + e)
            rec["task_index"] = int(task_index)
            recs.append(rec)
        return recs, acc


def _meta_worker(rank: int, algo: str, env_factory: Any, net_cfg: NetConfig, cfg: A3CConfig,
                 seed: int, psi: list[torch.Tensor], aux: dict[str, nn.Module],
                 grad_buf: list[torch.Tensor], inbox: Any, results: Any, threads: int) -> None:
    """Process target: run the tasks it is sent, write g_i into its shared buffer."""
    try:
        torch.set_num_threads(threads)
        torch.manual_seed(seed)
        runner = TaskRunner(algo, env_factory(), net_cfg, cfg, seed, aux)
        while True:
            job = inbox.get()
            if job is None:
                break
            task_index, first_episode, episodes = job
            recs, g = runner.run(psi, task_index, first_episode, episodes)
            with torch.no_grad():
                torch._foreach_copy_(grad_buf, g)
            results.put(("task", rank, recs))
    except BaseException:
        results.put(("error", rank, traceback.format_exc()))


class MetaTrainer(A3CTrainer):
    """Meta-training (see the module docstring) on the trainer machinery of A3C.

    Args:
        env_factory: environments holding all the meta-tasks (``options={"task": i}``).
        algo: the base algorithm: 'isar', 'savn' or 'a3c'.
        base_cfg: the base algorithm's config (its ``lr`` is the in-task Adam's).
        meta_cfg: episodes, workers, B, E, eta, the meta optimiser, seed, checkpoints.
        Other arguments as :class:`A3CTrainer`.
    """

    config_key = "base"

    def __init__(self, env_factory: Any, net_cfg: NetConfig | None, algo: str,
                 base_cfg: A3CConfig, meta_cfg: MetaConfig | None = None, *,
                 keep_task_grads: bool = False, **kwargs: Any) -> None:
        if algo not in WORKERS:
            raise ConfigError(f"meta-training base must be one of {sorted(WORKERS)}, "
                              f"not {algo!r}")
        check_a3c_base(base_cfg, PPO_BASE_META)
        self.algo = algo
        self.algorithm = f"meta-{algo}"
        self.meta_cfg = meta_cfg if meta_cfg is not None else MetaConfig()
        m = self.meta_cfg
        from dataclasses import replace

        base_cfg = replace(base_cfg, episodes=m.episodes, workers=m.workers, seed=m.seed,
                           checkpoint_every=0, torch_threads=m.torch_threads)
        super().__init__(env_factory, net_cfg, base_cfg, **kwargs)
        self.n_tasks = len(self.env.unwrapped.tasks)
        self.meta_updates = int(self.ckpt.meta.get("meta_updates", 0)
                                 if self.ckpt is not None else 0)
        self.keep_task_grads = keep_task_grads
        self.update_log: list[dict[str, Any]] = []
        """Per meta update: the task indices of the batch (and, with ``keep_task_grads``,
        psi before, the task gradients and psi after)."""

    # -- hooks -------------------------------------------------------------------------
    def build_aux(self) -> dict[str, nn.Module]:
        if self.algo == "savn":
            c = self.cfg
            return {"interaction_loss": InteractionLoss(c.k_steps,  # type: ignore[attr-defined]
                                                        c.tcn_channels)}  # type: ignore
        return {}

    def build_optimizer(self, params: list[torch.Tensor]) -> torch.optim.Optimizer:
        m = self.meta_cfg
        if m.meta_optimizer == "adam":
            return torch.optim.Adam(params, lr=m.meta_lr)
        return torch.optim.SGD(params, lr=m.meta_lr)

    def psi(self) -> list[torch.Tensor]:
        out = list(self.model.parameters())
        for mod in self.aux.values():
            out += list(mod.parameters())
        return out

    def resolved_config(self) -> dict[str, Any]:
        d = super().resolved_config()
        d["meta"] = to_dict(self.meta_cfg)
        d["base_algorithm"] = self.algo
        d["task_gradient"] = TASK_GRADIENT[self.algo]
        d["gradient_path"] = gradient_path(self.cfg)
        return d

    def checkpoint_meta(self, episodes: int) -> dict[str, Any]:
        meta = super().checkpoint_meta(episodes)
        meta["config"]["meta"] = to_dict(self.meta_cfg)
        meta["config"]["base_algorithm"] = self.algo
        meta["meta_updates"] = self.meta_updates
        return meta

    # -- the loop ----------------------------------------------------------------------
    def _next_batch(self) -> list[tuple[int, int, int]]:
        """(task index, first episode, episodes) of the next batch, cyclic from the
        number of task visits so far (so a resume continues the order)."""
        m = self.meta_cfg
        visits = self.episodes_done // m.episodes_per_task
        left = self.cfg.episodes - self.episodes_done
        jobs = []
        ep = self.episodes_done + 1
        for j in range(m.batch):
            if left <= 0:
                break
            n = min(m.episodes_per_task, left)
            jobs.append(((visits + j) % self.n_tasks, ep, n))
            ep += n
            left -= n
        return jobs

    def _meta_step(self, jobs: list[tuple[int, int, int]],
                   grads: list[list[torch.Tensor]]) -> None:
        entry = meta_step(self.optimizer, self.psi(), grads, self.meta_cfg.meta_max_grad_norm,
                          keep=self.keep_task_grads)
        self.meta_updates += 1
        self.update_log.append({"tasks": [j[0] for j in jobs], **entry})

    def _after_update(self, before: int, cbs: list[Callback], rng: Any) -> None:
        checkpoint_after_update(self, before, cbs, rng)

    def _records(self, recs: list[dict[str, Any]], cbs: list[Callback],
                 result: TrainResult) -> bool:
        go_on = True
        for rec in recs:
            rec["episode"] = self.episodes_done + 1
            rec["meta_update"] = self.meta_updates + 1
            go_on &= self._on_record(rec, cbs, result, lambda: None)
        return go_on

    def _train_inline(self, cbs: list[Callback], result: TrainResult) -> None:
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.torch_threads)
        try:
            runner = TaskRunner(self.algo, self.env, self.net_cfg, self.cfg, self.cfg.seed,
                                self.aux)
            if self.rng_state is not None:
                runner.worker.set_rng_state(self.rng_state)
            go_on = True
            while go_on and self.episodes_done < self.cfg.episodes:
                before = self.episodes_done
                jobs = self._next_batch()
                grads = []
                for ti, ep, n in jobs:
                    recs, g = runner.run(self.psi(), ti, ep, n)
                    grads.append(g)
                    go_on &= self._records(recs, cbs, result)
                self._meta_step(jobs, grads)
                self._after_update(before, cbs, runner.worker.rng_state)
            self._final_rng = runner.worker.rng_state()
        finally:
            torch.set_num_threads(threads)

    def _train_workers(self, cbs: list[Callback], result: TrainResult) -> None:
        ctx = torch.multiprocessing.get_context(self.mp_context)
        psi = self.psi()
        results = ctx.Queue()
        procs, inboxes, bufs = [], [], []
        for rank in range(self.cfg.workers):
            buf = [torch.zeros_like(p).share_memory_() for p in psi]
            inbox = ctx.Queue()
            seed = self.cfg.seed + 1000 * rank + 7919 * self.start_episode
            p = ctx.Process(target=_meta_worker, name=f"meta-worker-{rank}",
                            args=(rank, self.algo, self.env_factory, self.net_cfg, self.cfg,
                                  seed, psi, self.aux, buf, inbox, results,
                                  self.cfg.torch_threads), daemon=True)
            p.start()
            procs.append(p)
            inboxes.append(inbox)
            bufs.append(buf)
        try:
            go_on = True
            while go_on and self.episodes_done < self.cfg.episodes:
                before = self.episodes_done
                jobs = self._next_batch()
                grads: list[list[torch.Tensor]] = []
                # waves of at most W parallel tasks; records are logged in batch order
                for w0 in range(0, len(jobs), len(procs)):
                    wave = jobs[w0:w0 + len(procs)]
                    for r, job in enumerate(wave):
                        inboxes[r].put(job)
                    got: dict[int, list[dict[str, Any]]] = {}
                    while len(got) < len(wave):
                        try:
                            kind, rank, payload = results.get(timeout=0.5)
                        except queue_mod.Empty:
                            dead = [i for i, p in enumerate(procs) if p.exitcode is not None]
                            if dead:
                                raise WorkerFailed(f"meta worker {dead[0]} died with exit "
                                                   f"code {procs[dead[0]].exitcode}") from None
                            continue
                        if kind == "error":
                            raise WorkerFailed(f"meta worker {rank} failed:\n{payload}")
                        got[rank] = payload
                    for r in range(len(wave)):
                        grads.append([b.clone() for b in bufs[r]])
                        go_on &= self._records(got[r], cbs, result)
                self._meta_step(jobs, grads)
                self._after_update(before, cbs, lambda: None)
        finally:
            for inbox in inboxes:
                inbox.put(None)
            for p in procs:
                p.join(timeout=10)
                if p.is_alive():
                    p.terminate()
                    p.join()


def meta_train(env_factory: Any, net_cfg: NetConfig | None, algo: str, base_cfg: A3CConfig,
               meta_cfg: MetaConfig | None = None, **kwargs: Any) -> TrainResult:
    """Build a :class:`MetaTrainer` and run it."""
    return MetaTrainer(env_factory, net_cfg, algo, base_cfg, meta_cfg, **kwargs).train()


__all__ = ["MetaTrainer", "TaskRunner", "meta_train", "meta_step", "checkpoint_after_update",
           "TASK_GRADIENT"]
