"""A3C (ALGORITHMS.md (a)): W worker processes, one shared model, a shared Adam.

Per episode (random start, zero LSTM state), until done, each worker:

1. syncs its local network from the shared one;
2. acts ``t_max`` steps without autograd (``inference_mode``), storing the inputs;
3. recomputes the rollout's forward in one batch from the stored start state
   (the CNN sees all T views in one call; the LSTM runs its T steps), takes
   L_AC (:mod:`geonav.policy.losses`), backpropagates and clips the norm to 100;
4. hands its gradients to the shared parameters and steps the shared Adam;
5. carries the state on (it never had a graph: step 5's "detach h").

Step 3 gives the same loss and gradient as keeping a graph per step (the same
parameters produce the same numbers; see ``tests/test_policy_losses.py``), with
a far cheaper backward. ``workers=0`` runs one worker in this process,
deterministically for a seed, and can resume bit-exactly.
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue as queue_mod
import sys
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from geonav.errors import ConfigError, GeonavError, TrainingDiverged
from geonav.policy.agent import choose_action, obs_inputs
from geonav.policy.callbacks import Callback, CSVMetrics, plot_learning_curve, tensorboard_callback
from geonav.policy.checkpoint import check_compatible, load_checkpoint, make_meta, save_checkpoint
from geonav.policy.config import A3CConfig, NetConfig, to_dict
from geonav.policy.encoders import FrozenEncoder, build_frozen_encoder
from geonav.policy.evaluation import spl
from geonav.policy.losses import actor_critic_loss
from geonav.policy.model import ActorCritic, State
from geonav.policy.optim import SharedAdam, warm_up_lr

log = logging.getLogger(__name__)

EnvFactory = Callable[[], Any]


def truncate_csv(path: Path, last_episode: int) -> None:
    """Drop the rows of a run CSV logged after ``last_episode`` (resume from a checkpoint)."""
    import csv

    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
        fields = list(rows[0].keys()) if rows else None
    if fields is None:
        return
    keep = [r for r in rows if int(float(r["episode"])) <= last_episode]
    if len(keep) == len(rows):
        return
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(keep)
    os.replace(tmp, path)


class WorkerFailed(GeonavError):
    """A training worker process raised or died; the message holds its traceback."""


@dataclass
class Rollout:
    """Up to ``t_max`` steps of one episode, stored for the batched loss recompute."""

    start_state: State
    target: torch.Tensor
    views: list[torch.Tensor] = field(default_factory=list)
    actions: list[int] = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.actions)


def _plain_state(state: State) -> State:
    """A graph-free copy of a recurrent state that autograd may save (not an inference tensor)."""
    return (state[0].detach().clone(), state[1].detach().clone(), state[2].detach().clone())


def rollout_loss(model: nn.Module, rollout: Rollout, bootstrap: float, cfg: A3CConfig,
                 params: dict[str, torch.Tensor] | None = None) -> Any:
    """L_AC of a stored rollout, recomputed in one forward call from its start state.

    Args:
        model: the actor-critic.
        rollout: the stored steps.
        bootstrap: B (0 when the rollout ended the episode).
        cfg: trainer config (its ``loss``).
        params: optional name -> tensor dict for ``functional_call`` (SAVN/ISAR).
    """
    views = torch.stack(rollout.views).unsqueeze(1)            # (T, 1, ...)
    args = (views, rollout.target.unsqueeze(0), rollout.start_state)
    if params is None:
        logits, values, _ = model(*args)
    else:
        logits, values, _ = torch.func.functional_call(model, params, args, strict=True)
    return actor_critic_loss(logits[:, 0], values[:, 0], rollout.actions, rollout.rewards,
                             bootstrap, cfg.loss)


class A3CWorker:
    """One A3C worker: a local network, an env, and the shared model and optimiser.

    With ``shared_model=None`` the local network *is* the shared one (single process).
    """

    def __init__(self, rank: int, model: ActorCritic, optimizer: torch.optim.Optimizer,
                 env: Any, cfg: A3CConfig, frozen: FrozenEncoder | None, seed: int,
                 shared_model: ActorCritic | None = None,
                 rng_state: dict[str, Any] | None = None) -> None:
        self.rank = rank
        self.model = model
        self.shared = shared_model
        self.optimizer = optimizer
        self.env = env
        self.cfg = cfg
        self.frozen = frozen
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self._env_seeded = False
        self.env_steps = 0
        self.reset_options: dict[str, Any] | None = None
        """Options of the next ``env.reset`` (meta-training picks the task with them)."""
        self.on_gradients: Callable[[list[torch.Tensor]], None] | None = None
        """Called with the unclipped gradients of every update before the optimiser steps
        (meta-training sums them into the task gradient)."""
        self._params: list[torch.Tensor] = list(model.parameters())
        self._shared_params: list[torch.Tensor] | None = list(shared_model.parameters()) \
            if shared_model is not None else None
        if rng_state is not None:
            self.set_rng_state(rng_state)

    @classmethod
    def create(cls, rank: int, shared_model: ActorCritic, optimizer: torch.optim.Optimizer,
               env: Any, net_cfg: NetConfig, cfg: A3CConfig, frozen: FrozenEncoder | None,
               seed: int, extra: dict[str, Any] | None = None) -> A3CWorker:
        """The worker of a worker process: a local copy of the shared network.

        ``extra`` carries what subclasses share beyond the policy (see
        :meth:`A3CTrainer.worker_extra`).
        """
        local = ActorCritic(net_cfg)
        local.load_state_dict(shared_model.state_dict())
        return cls(rank, local, optimizer, env, cfg, frozen, seed, shared_model=shared_model)

    def reset_env(self) -> tuple[Any, dict[str, Any]]:
        """``env.reset``, seeded on the first call, with :attr:`reset_options`."""
        if not self._env_seeded:
            self._env_seeded = True
            return self.env.reset(seed=self.seed, options=self.reset_options)
        return self.env.reset(options=self.reset_options)

    # -- RNG state (exact resume in single-process mode) ----------------------------------
    def rng_state(self) -> dict[str, Any]:
        return {"torch": torch.get_rng_state(), "numpy": self.rng.bit_generator.state,
                "env": self.env.unwrapped.np_random.bit_generator.state,
                "env_seeded": self._env_seeded}

    def set_rng_state(self, st: dict[str, Any]) -> None:
        torch.set_rng_state(st["torch"])
        self.rng.bit_generator.state = st["numpy"]
        self.env.unwrapped.np_random.bit_generator.state = st["env"]
        self._env_seeded = bool(st["env_seeded"])

    # -- the algorithm --------------------------------------------------------------------
    def sync(self) -> None:
        """Step 1: local parameters <- shared parameters."""
        if self._shared_params is not None:
            with torch.no_grad():
                torch._foreach_copy_(self._params, self._shared_params)

    def update(self, rollout: Rollout, bootstrap: float) -> Any:
        """Steps 3-4: batched recompute, L_AC, backward, clip, shared Adam step."""
        for p in self._params:
            p.grad = None
        loss = rollout_loss(self.model, rollout, bootstrap, self.cfg)
        loss.total.backward()
        self.apply_gradients()
        return loss

    def apply_gradients(self) -> None:
        """Show the local ``.grad`` to :attr:`on_gradients` (unclipped), clip it to
        ``max_grad_norm``, hand it to the shared parameters and step the shared optimiser."""
        if self.on_gradients is not None:
            self.on_gradients([p.grad for p in self._params])  # type: ignore[misc]
        if self.cfg.max_grad_norm:
            nn.utils.clip_grad_norm_(self._params, self.cfg.max_grad_norm)
        if self._shared_params is not None:
            for p, sp in zip(self._params, self._shared_params, strict=True):
                sp.grad = p.grad
        warm_up_lr(self.optimizer, self.cfg.lr, self.cfg.lr_warmup)
        self.optimizer.step()

    def run_episode(self, episode: int) -> dict[str, Any]:
        """Play one training episode, updating every ``t_max`` steps; returns its record."""
        t0 = time.perf_counter()
        cfg = self.cfg
        obs, info = self.reset_env()
        shortest = int(info["shortest_path"])
        state = self.model.initial_state()
        ep_return, length, collisions = 0.0, 0, 0
        pl = vl = ent = 0.0
        n_updates = 0
        terminated = truncated = False
        view, target = obs_inputs(obs, info, self.frozen)
        while not (terminated or truncated):
            self.sync()
            # Clone: the state may come from inference mode, and the recompute needs a
            # plain tensor as its (constant) start.
            ro = Rollout(_plain_state(state), target)
            with torch.inference_mode():  # ~25% cheaper than no_grad for batch-1 steps
                target_feat = self.model.features(target[None])  # once per rollout
                for _ in range(cfg.t_max):
                    logits, _, state = self.model(view[None, None], target_feat, state)
                    a = choose_action(logits[0, 0], False, self.rng)
                    obs, r, terminated, truncated, info = self.env.step(a)
                    ro.views.append(view)
                    ro.actions.append(a)
                    ro.rewards.append(float(r))
                    ep_return += float(r)
                    length += 1
                    collisions += int(bool(info["collided"]))
                    view, _ = obs_inputs(obs, info, self.frozen)
                    if terminated or truncated:
                        break
                if terminated or (truncated and not cfg.loss.bootstrap_on_truncation):
                    bootstrap = 0.0
                else:  # V(s_next): an extra forward that does not advance the state
                    _, v_next, _ = self.model(view[None, None], target_feat, state)
                    bootstrap = float(v_next[0, 0])
            loss = self.update(ro, bootstrap)
            pl += loss.policy.item()
            vl += loss.value.item()
            ent += loss.entropy.item() / len(ro)
            n_updates += 1
        self.env_steps += length
        success = bool(info["success"])
        return {"episode": episode, "worker": self.rank, "task": info["task"],
                "task_index": int(info["task_index"]), "return": ep_return, "length": length,
                "success": success, "spl": spl(success, shortest, length),
                "collisions": collisions, "shortest_path": shortest,
                "policy_loss": pl / n_updates, "value_loss": vl / n_updates,
                "entropy": ent / n_updates, "env_steps": length,
                "wall_s": time.perf_counter() - t0}


def _worker_process(rank: int, shared_model: ActorCritic, optimizer: SharedAdam,
                    env_factory: EnvFactory, net_cfg: NetConfig, cfg: A3CConfig, seed: int,
                    counter: Any, lock: Any, results: Any, stop: Any, ready: Any,
                    worker_cls: type[A3CWorker] = A3CWorker,
                    extra: dict[str, Any] | None = None) -> None:
    """Process target: claim episode numbers from the global counter until the budget is spent."""
    try:
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(seed)
        env = env_factory()
        worker = worker_cls.create(rank, shared_model, optimizer, env, net_cfg, cfg,
                                   build_frozen_encoder(net_cfg), seed, extra)
        ready.wait(timeout=300)  # start together, so every worker takes part from episode 1
        while not stop.is_set():
            with lock:
                if counter.value >= cfg.episodes:
                    break
                counter.value += 1
                episode = counter.value
            results.put(("episode", rank, worker.run_episode(episode)))
        results.put(("done", rank, None))
    except BaseException:  # report everything, including KeyboardInterrupt, to the main process
        results.put(("error", rank, traceback.format_exc()))


@dataclass
class TrainResult:
    """What a training run produced."""

    model: ActorCritic
    episodes: int
    """Episodes completed in total (including those of a resumed checkpoint)."""
    env_steps: int
    """Environment steps taken by this call."""
    wall_s: float
    start_episode: int
    checkpoint: Path | None = None
    out_dir: Path | None = None
    records: list[dict[str, Any]] = field(default_factory=list, repr=False)
    evals: list[dict[str, Any]] = field(default_factory=list, repr=False)
    """Rows of the periodic greedy/sampled evaluations of this call (see eval.csv)."""
    eval_s: float = 0.0
    """Seconds of this call spent in periodic evaluation (inside ``wall_s``)."""

    @property
    def steps_per_s(self) -> float:
        return self.env_steps / max(self.wall_s, 1e-9)


LOSS_FIELDS = ("policy_loss", "value_loss", "entropy")
"""Per-episode loss figures of a training record (the metrics CSV's columns)."""


def check_finite_losses(rec: dict[str, Any]) -> None:
    """Raise :class:`TrainingDiverged` when an episode's recorded losses are NaN or infinite.

    Called after the callbacks have seen the record, so the metrics CSV keeps the row that
    shows the divergence; without it a diverged run fails later and obscurely (a NaN
    probability in the next evaluation's sampling) or trains on as NaN.
    """
    bad = [k for k in LOSS_FIELDS
           if isinstance(rec.get(k), (int, float)) and not math.isfinite(rec[k])]
    if bad:
        raise TrainingDiverged(
            f"training diverged at episode {rec.get('episode')}: "
            f"{', '.join(f'{k} = {rec[k]}' for k in bad)}. The metrics CSV shows the losses "
            f"growing before it; lower lr (meta_lr for meta-training), or clip gradients "
            f"(max_grad_norm; meta_max_grad_norm for meta-training)")


class _ReleaseLock(Callback):
    """Releases a run folder's write lock when training ends (also after an error)."""

    def __init__(self, lock: Any) -> None:
        self.lock = lock

    def on_train_end(self, result: Any) -> None:
        if self.lock is not None:
            self.lock.__exit__(None, None, None)
            self.lock = None


class A3CTrainer:
    """Trains an :class:`ActorCritic` with A3C on environments from ``env_factory``.

    Args:
        env_factory: a picklable callable returning a fresh environment (called in
            every worker process, and once here for metadata and checks).
        net_cfg: the architecture (ignored when resuming: the checkpoint's is used,
            and a different explicit one is refused).
        cfg: A3C settings.
        out_dir: run folder (config.json, metrics.csv, checkpoints/, learning_curve.png);
            None keeps everything in memory.
        resume: a checkpoint to continue from (episodes, weights, Adam state, RNG).
        callbacks: extra :class:`Callback` objects (progress bars, early stopping).
        mp_context: process start method: 'fork' (default on Linux: workers start at once;
            each sets one torch thread before any work), 'spawn' (default elsewhere; each
            worker re-imports torch, several seconds) or 'forkserver'.
        keep_records: keep every episode record in ``TrainResult.records``.
        tensorboard: a folder for TensorBoard event files under SB3's tag names, x = env
            steps (``True``: ``out_dir/tb``); None (default) logs none. Needs the
            ``tensorboard`` extra.
    """

    algorithm = "a3c"
    config_key = "a3c"
    """Key of the algorithm's config in config.json and the checkpoint meta."""
    worker_cls: type[A3CWorker] = A3CWorker

    def __init__(self, env_factory: EnvFactory, net_cfg: NetConfig | None = None,
                 cfg: A3CConfig | None = None, *, out_dir: str | os.PathLike[str] | None = None,
                 resume: str | os.PathLike[str] | None = None,
                 callbacks: Sequence[Callback] = (), mp_context: str | None = None,
                 keep_records: bool = True,
                 tensorboard: str | os.PathLike[str] | bool | None = None) -> None:
        if mp_context is None:
            mp_context = "fork" if "fork" in torch.multiprocessing.get_all_start_methods() \
                and sys.platform.startswith("linux") else "spawn"
        if mp_context not in ("spawn", "fork", "forkserver"):
            raise ConfigError(f"mp_context must be spawn, fork or forkserver, not {mp_context!r}")
        cfg = cfg if cfg is not None else A3CConfig()
        self.env_factory = env_factory
        self.cfg = cfg
        self.mp_context = mp_context
        self.keep_records = keep_records
        self.tensorboard = tensorboard
        self.callbacks = list(callbacks)
        self.env = env_factory()
        # Validate the resume checkpoint before touching the run folder.
        self.ckpt = load_checkpoint(resume) if resume is not None else None
        if self.ckpt is not None:
            check_compatible(self.ckpt.meta, self.env, path=self.ckpt.path, net_cfg=net_cfg)
            net_cfg = self.ckpt.net_config
        self.net_cfg = net_cfg or NetConfig(
            obs_size_px=int(self.env.observation_space["image"].shape[0]))
        n_env = int(self.env.observation_space["image"].shape[0])
        if self.net_cfg.obs_size_px != n_env:
            raise ConfigError(f"the network expects {self.net_cfg.obs_size_px} px views, the "
                              f"environment gives {n_env} px; set obs_size_px={n_env}")
        if self.net_cfg.n_actions != int(self.env.action_space.n):
            raise ConfigError(f"the network has {self.net_cfg.n_actions} actions, the env "
                              f"{self.env.action_space.n}")
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self._check_new_run_folder()
        self.frozen = build_frozen_encoder(self.net_cfg)
        torch.manual_seed(cfg.seed)
        self.model = ActorCritic(self.net_cfg)
        self.aux: dict[str, nn.Module] = self.build_aux()
        params: list[torch.Tensor] = list(self.model.parameters())
        for m in self.aux.values():
            params += list(m.parameters())
        self.optimizer = self.build_optimizer(params)
        self.start_episode = 0
        self.rng_state: dict[str, Any] | None = None
        if self.ckpt is not None:
            self.model.load_state_dict(self.ckpt.model_state)
            for name, m in self.aux.items():
                if not self.ckpt.extra or name not in self.ckpt.extra:
                    raise ConfigError(f"{self.ckpt.path} holds no {name!r} state; it was not "
                                      f"written by a {self.algorithm} run")
                m.load_state_dict(self.ckpt.extra[name])
            if self.ckpt.optimizer_state is not None:
                self.optimizer.load_state_dict(self.ckpt.optimizer_state)
            self.start_episode = self.ckpt.episodes
            rng = self.ckpt.rng
            # another engine's random streams do not fit this one's (resume across engines)
            if rng is None or (rng.get("engine") == "batched") == \
                    (getattr(self, "engine", None) == "batched"):
                self.rng_state = rng
        self.model.share_memory()
        for m in self.aux.values():
            m.share_memory()
        self.episodes_done = self.start_episode
        self._eval_env: Any = None
        self._eval_writer: Any = None
        self._last_eval = -1
        self.eval_s = 0.0
        """Seconds spent in periodic evaluation by this call of :meth:`train`."""
        if self.ckpt is not None and self.out_dir is not None:
            truncate_csv(self.out_dir / "eval.csv", self.start_episode)
            truncate_csv(self.out_dir / "metrics.csv", self.start_episode)  # no duplicate rows

    # -- hooks for the algorithms built on this trainer (SAVN, ISAR) ----------------------
    def build_optimizer(self, params: list[torch.Tensor]) -> torch.optim.Optimizer:
        """The shared optimiser (SharedAdam); meta-training uses its own."""
        cfg = self.cfg
        return SharedAdam(params, lr=cfg.lr, betas=cfg.adam_betas, eps=cfg.adam_eps,
                          amsgrad=cfg.amsgrad, fused=cfg.fused)

    def build_aux(self) -> dict[str, nn.Module]:
        """Shared modules trained beside the policy (name -> module); A3C has none."""
        return {}

    def worker_extra(self) -> dict[str, Any] | None:
        """What :meth:`A3CWorker.create` receives besides the policy in each process."""
        return {"aux": self.aux} if self.aux else None

    def inline_worker(self) -> A3CWorker:
        """The worker of the single-process mode (acts on the shared model itself)."""
        return self.worker_cls(0, self.model, self.optimizer, self.env, self.cfg, self.frozen,
                               self.cfg.seed, rng_state=self.rng_state)

    # -- run folder -------------------------------------------------------------------------
    def resolved_config(self) -> dict[str, Any]:
        env = make_meta(self.net_cfg, self.frozen, self.env, algorithm=self.algorithm,
                        episodes=self.start_episode)
        return {"algorithm": self.algorithm, "net": to_dict(self.net_cfg),
                self.config_key: to_dict(self.cfg), "env": env,
                "resume": str(self.ckpt.path) if self.ckpt is not None else None,
                "start_episode": self.start_episode, "mp_context": self.mp_context,
                "augment": _augment_of(self.env)}

    def _check_new_run_folder(self) -> None:
        """A new run (no resume) refuses a folder whose files it would overwrite."""
        if self.out_dir is None or self.ckpt is not None:
            return
        from geonav.outputs import run_folder_conflicts

        names, ours = run_folder_conflicts(self.out_dir)
        if names and ours:
            raise ConfigError(f"run folder {self.out_dir} already holds a run; pass --resume "
                              f"{self.out_dir / 'checkpoints' / 'latest.pt'} or another --out")
        if names:
            raise ConfigError(f"run folder {self.out_dir} holds {', '.join(names)}, which "
                              "geonav did not write and a run would overwrite; choose another "
                              "--out (a new or empty folder)")

    def _prepare_out_dir(self) -> list[Callback]:
        if self.out_dir is None:
            return []
        from geonav.outputs import output_lock

        # Held until on_train_end: a second run into this folder is refused, not mixed in.
        lock = output_lock(self.out_dir, "--out")
        lock.__enter__()
        try:
            self._check_new_run_folder()  # again: another run may have written it since
            cbs = self._write_run_config()
        except BaseException:
            lock.__exit__(None, None, None)
            raise
        return [_ReleaseLock(lock), *cbs]

    def _write_run_config(self) -> list[Callback]:
        assert self.out_dir is not None
        (self.out_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        cfg_path = self.out_dir / "config.json"
        if cfg_path.exists() and self.ckpt is not None:  # keep the original beside the resume
            os.replace(cfg_path, self.out_dir / f"config.before_resume_{self.start_episode}.json")
        tmp = cfg_path.with_name(".config.json.tmp")
        tmp.write_text(json.dumps(self.resolved_config(), indent=1))
        os.replace(tmp, cfg_path)
        cbs: list[Callback] = [CSVMetrics(self.out_dir / "metrics.csv")]
        return cbs

    def _tensorboard(self) -> list[Callback]:
        if self.tensorboard is None or self.tensorboard is False:
            return []
        if self.tensorboard is True:
            if self.out_dir is None:
                raise ConfigError("tensorboard=True needs a run folder; pass a folder instead")
            folder: Any = self.out_dir / "tb"
        else:
            folder = self.tensorboard
        tb = tensorboard_callback(folder, required=True)
        return [tb] if tb is not None else []

    def checkpoint_meta(self, episodes: int) -> dict[str, Any]:
        return make_meta(self.net_cfg, self.frozen, self.env, algorithm=self.algorithm,
                         episodes=episodes, config={self.config_key: to_dict(self.cfg)})

    def save(self, path: str | os.PathLike[str], episodes: int,
             rng: dict[str, Any] | None = None) -> Path:
        """Write a checkpoint of the shared model and optimiser."""
        return save_checkpoint(path, self.model.state_dict(), self.checkpoint_meta(episodes),
                               self.optimizer.state_dict(), rng,
                               {name: m.state_dict() for name, m in self.aux.items()} or None)

    # -- training ---------------------------------------------------------------------------
    def train(self) -> TrainResult:
        """Run until ``cfg.episodes`` episodes in total; write the final checkpoint."""
        cbs, result = self.begin_training()
        try:
            if self.cfg.workers == 0:
                self._train_inline(cbs, result)
            else:
                self._train_workers(cbs, result)
            self.finish_training(cbs, result)
        finally:
            for cb in cbs:
                cb.on_train_end(result)
        return result

    def begin_training(self) -> tuple[list[Callback], TrainResult]:
        """The run folder, callbacks and result of a :meth:`train` call (packed runs call
        this, the loop of their driver, then :meth:`finish_training` per member)."""
        cbs = self._prepare_out_dir() + self._tensorboard() + self.callbacks
        self._t_start = time.perf_counter()
        self._elapsed_base = self._resumed_elapsed()
        result = TrainResult(self.model, self.start_episode, 0, 0.0, self.start_episode,
                             out_dir=self.out_dir)
        self._eval_every = self.eval_interval()
        for cb in cbs:
            cb.on_train_start({"episodes": self.cfg.episodes, "start_episode": self.start_episode,
                               "workers": self.cfg.workers, "out_dir": self.out_dir,
                               "total_steps": self.cfg.total_steps,
                               "start_env_steps": self.total_env_steps(result),
                               "algorithm": self.algorithm,
                               "reports_updates": self.reports_updates})
        return cbs, result

    def finish_training(self, cbs: list[Callback], result: TrainResult) -> None:
        """After the loop: the final evaluation, final.pt and latest.pt, the curve."""
        if self._eval_every and self._last_eval != self.episodes_done:  # the final policy
            self.evaluate_now(cbs, result)
        result.wall_s = time.perf_counter() - self._t_start
        result.eval_s = self.eval_s
        result.episodes = self.episodes_done
        if self.out_dir is not None:
            ck = self.out_dir / "checkpoints"
            rng = self._final_rng
            result.checkpoint = self.save(ck / "final.pt", self.episodes_done, rng)
            self.save(ck / "latest.pt", self.episodes_done, rng)
            for cb in cbs:
                cb.on_checkpoint(result.checkpoint, self.episodes_done)
            metrics = self.out_dir / "metrics.csv"
            for cb in cbs:
                if isinstance(cb, CSVMetrics):
                    cb.close()
            if metrics.exists():
                plot_learning_curve(metrics, self.out_dir / "learning_curve.png")

    reports_updates = False
    """Whether :meth:`train` calls the callbacks' ``on_update`` (the batched engine does;
    here the updates happen in the workers, and each episode's record carries its losses)."""
    _final_rng: dict[str, Any] | None = None
    _t_start: float = 0.0
    _elapsed_base: float = 0.0

    def _resumed_elapsed(self) -> float:
        """Training seconds already spent by the run being resumed (0 for a new run)."""
        if self.ckpt is None or self.out_dir is None:
            return 0.0
        metrics = self.out_dir / "metrics.csv"
        if not metrics.exists():
            return 0.0
        from geonav.policy.callbacks import read_metrics

        rows = [r for r in read_metrics(metrics) if r["episode"] <= self.start_episode]
        self._steps_base = int(sum(int(r.get("length") or 0) for r in rows))
        done = [r for r in rows if r.get("elapsed_s") is not None]
        return float(done[-1]["elapsed_s"]) if done else 0.0

    # -- periodic evaluation (issue 10: greedy and sampled from every start) --------------
    def eval_interval(self) -> int:
        """Episodes between periodic evaluations (0: none, not even at the end)."""
        every = self.cfg.eval_every
        if every != -1:
            return every
        from geonav.policy.evaluation import all_starts

        n = len(all_starts(self.env, self.cfg.eval_max_starts, self.cfg.seed))
        return int(math.ceil(5 * n / 10.0) * 10)

    def evaluate_now(self, cbs: list[Callback], result: TrainResult) -> dict[str, Any]:
        """Evaluate a snapshot of the live policy; append the row to eval.csv and tell
        the callbacks."""
        import copy

        from geonav.policy.evaluation import EVAL_FIELDS, evaluate_both

        t0 = time.perf_counter()
        if self._eval_env is None:
            self._eval_env = self.env_factory()
        snapshot = copy.deepcopy(self.model)  # no RNG draw; workers may step the original
        res = evaluate_both(snapshot, self._eval_env, frozen=self.frozen,
                            max_starts=self.cfg.eval_max_starts, seed=self.cfg.seed,
                            threads=self.cfg.torch_threads)
        self.eval_s += time.perf_counter() - t0
        row = {"episode": self.episodes_done, "env_steps": self.total_env_steps(result),
               "elapsed_s": round(self._elapsed_base + time.perf_counter() - self._t_start, 3),
               "eval_s": round(time.perf_counter() - t0, 3), **res["row"]}
        self._last_eval = self.episodes_done
        if self.out_dir is not None:
            import csv

            path = self.out_dir / "eval.csv"
            new = not path.exists() or path.stat().st_size == 0
            fields: tuple[str, ...] = (*EVAL_FIELDS, "eval_s")
            if not new:  # a resumed run appends in the file's own columns (older: fewer)
                with open(path, newline="") as f:
                    fields = tuple(next(csv.reader(f), []) or fields)
            with open(path, "a", newline="") as f:
                w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
                if new:
                    w.writeheader()
                w.writerow(row)
        result.evals.append(row)
        for cb in cbs:  # duck-typed callbacks may lack the hook
            hook = getattr(cb, "on_eval", None)
            if hook is not None:
                hook(row)
        return row

    def total_env_steps(self, result: TrainResult) -> int:
        """Env steps of the whole run so far (resumed episodes included when known)."""
        return int(self._steps_base + result.env_steps)

    _steps_base: int = 0

    def _on_record(self, rec: dict[str, Any], cbs: list[Callback], result: TrainResult,
                   rng: Callable[[], dict[str, Any] | None]) -> bool:
        """Handle one finished episode in the main process; False asks to stop."""
        self.episodes_done += 1
        result.env_steps += int(rec["length"])
        rec["env_steps"] = self.total_env_steps(result)  # running total, resumes included
        rec["elapsed_s"] = round(self._elapsed_base + time.perf_counter() - self._t_start, 3)
        if self.keep_records:
            result.records.append(rec)
        go_on = True
        for cb in cbs:
            if cb.on_episode(rec) is False:
                go_on = False
        check_finite_losses(rec)
        if self._eval_every and self.episodes_done % self._eval_every == 0:
            self.evaluate_now(cbs, result)
        if self.cfg.total_steps and rec["env_steps"] >= self.cfg.total_steps:
            go_on = False  # the step budget is spent
        every = self.cfg.checkpoint_every
        if self.out_dir is not None and every and self.episodes_done % every == 0:
            path = self.save(self.out_dir / "checkpoints" / "latest.pt", self.episodes_done,
                             rng())
            if self.cfg.keep_checkpoints:
                self.save(self.out_dir / "checkpoints" / f"episode_{self.episodes_done}.pt",
                          self.episodes_done, rng())
            for cb in cbs:
                cb.on_checkpoint(path, self.episodes_done)
        return go_on

    def _train_inline(self, cbs: list[Callback], result: TrainResult) -> None:
        threads = torch.get_num_threads()
        torch.set_num_threads(self.cfg.torch_threads)
        try:
            worker = self.inline_worker()
            while self.episodes_done < self.cfg.episodes:
                rec = worker.run_episode(self.episodes_done + 1)
                if not self._on_record(rec, cbs, result, worker.rng_state):
                    break
            self._final_rng = worker.rng_state()
        finally:
            torch.set_num_threads(threads)

    def _train_workers(self, cbs: list[Callback], result: TrainResult) -> None:
        ctx: Any = torch.multiprocessing.get_context(self.mp_context)
        counter = ctx.Value("l", self.episodes_done)
        lock = ctx.Lock()
        results = ctx.Queue()
        stop = ctx.Event()
        ready = ctx.Barrier(self.cfg.workers)
        procs = []
        for rank in range(self.cfg.workers):
            # Distinct streams per worker, and new ones after a resume.
            seed = self.cfg.seed + 1000 * rank + 7919 * self.start_episode
            p = ctx.Process(target=_worker_process, name=f"{self.algorithm}-worker-{rank}",
                            args=(rank, self.model, self.optimizer, self.env_factory,
                                  self.net_cfg, self.cfg, seed, counter, lock, results, stop,
                                  ready, self.worker_cls, self.worker_extra()),
                            daemon=True)
            p.start()
            procs.append(p)
        finished: set[int] = set()
        error: str | None = None
        try:
            while len(finished) < len(procs):
                try:
                    kind, rank, payload = results.get(timeout=0.5)
                except queue_mod.Empty:
                    dead = [i for i, p in enumerate(procs)
                            if i not in finished and p.exitcode not in (None, 0)]
                    if dead:
                        error = f"worker {dead[0]} died with exit code {procs[dead[0]].exitcode}"
                        break
                    continue
                if kind == "episode":
                    if not self._on_record(payload, cbs, result, lambda: None):
                        stop.set()
                elif kind == "done":
                    finished.add(rank)
                else:
                    error = f"worker {rank} failed:\n{payload}"
                    break
        finally:
            stop.set()
            ready.abort()  # frees workers still waiting at the start barrier
            for p in procs:
                p.join(timeout=10)
                if p.is_alive():
                    p.terminate()
                    p.join()
        if error is not None:
            raise WorkerFailed(error)


def _augment_of(env: Any) -> dict[str, Any] | None:
    """The imagery randomisation of the training env (geonav.augment), for config.json."""
    from geonav.vecenv import find_augment

    cfg = find_augment(env)
    return None if cfg is None else cfg.to_dict()


def train_a3c(env_factory: EnvFactory, net_cfg: NetConfig | None = None,
              cfg: A3CConfig | None = None, **kwargs: Any) -> TrainResult:
    """Build an :class:`A3CTrainer` and run it (see its arguments)."""
    return A3CTrainer(env_factory, net_cfg, cfg, **kwargs).train()
