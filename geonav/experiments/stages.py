"""Execute one experiment unit: a training stage for one seed, then its evaluation.

The payload (built by the runner) names the mode ("train", "meta-train",
"curriculum"), the algorithm, the scene and task set, the episode budget, the
seed, an optional ``init_checkpoint`` to start from (weights only: a
fine-tune starts its own episode count and optimiser) and the unit folder.
A unit folder that already holds ``checkpoints/latest.pt`` is resumed from
it, so a killed experiment loses at most one checkpoint interval.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from geonav.errors import ConfigError

log = logging.getLogger(__name__)

#: mode -> algo -> function(payload, env_factory, callbacks, resume) -> (model, episodes, ckpt)
TRAINERS: dict[tuple[str, str], Callable[..., Any]] = {}


def trainer(mode: str, *algos: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Register a stage trainer for (mode, algo) pairs."""

    def deco(fn: Callable[..., Any]) -> Callable[..., Any]:
        for algo in algos:
            TRAINERS[(mode, algo)] = fn
        return fn

    return deco


class ProgressFile:
    """A trainer callback that keeps ``progress.json`` up to date (read by the runner)."""

    def __init__(self, path: Path, every_s: float = 1.0) -> None:
        self.path = path
        self.every_s = every_s
        self._last = 0.0

    def on_train_start(self, info: dict[str, Any]) -> None:
        self._write(int(info.get("start_episode", 0)))

    def on_episode(self, record: dict[str, Any]) -> None:
        now = time.monotonic()
        if now - self._last >= self.every_s:
            self._last = now
            self._write(int(record.get("episode", 0)))

    def on_checkpoint(self, path: Any, episodes: int) -> None:
        self._write(episodes)

    def on_train_end(self, result: Any) -> None:
        pass

    def _write(self, episodes: int) -> None:
        tmp = self.path.with_name(".progress.tmp")
        tmp.write_text(json.dumps({"episodes": episodes, "time": time.time()}))
        os.replace(tmp, self.path)


class ConvergenceStop:
    """Stops a training stage once both convergence rules are confirmed: the training-SR
    e* (found and held for W more episodes) and the evaluation e* (two consecutive greedy
    evaluations over all starts at ``eval_threshold``), so budgets are upper bounds and
    both e* are known when it stops."""

    def __init__(self, criterion: Any, successes: list[bool] | None = None,
                 evals: list[tuple[int, float]] | None = None) -> None:
        self.criterion = criterion
        self.successes = list(successes or [])
        self.evals = list(evals or [])
        self.converged_at: int | None = None
        self.eval_converged_at: int | None = None

    def on_train_start(self, info: dict[str, Any]) -> None:
        pass

    def on_eval(self, row: dict[str, Any]) -> None:
        from geonav.convergence import eval_convergence

        self.evals.append((int(row["episode"]), float(row["greedy_sr"])))
        ep, sr = zip(*self.evals, strict=True)
        self.eval_converged_at = eval_convergence(ep, sr, 0,
                                                  self.criterion.eval_threshold).episodes

    def on_episode(self, record: dict[str, Any]) -> bool | None:
        from geonav.convergence import episodes_to_convergence

        self.successes.append(bool(record.get("success")))
        w = self.criterion.window
        # check once per W/10 episodes: cheap and at most W/10 episodes late
        if self.converged_at is None and len(self.successes) % max(1, w // 10) == 0:
            self.converged_at = episodes_to_convergence(self.successes,
                                                        self.criterion).episodes
        if self.converged_at is not None and self.eval_converged_at is not None:
            return False
        return None

    def on_checkpoint(self, path: Any, episodes: int) -> None:
        pass

    def on_train_end(self, result: Any) -> None:
        pass


def _load_init(model: Any, path: str | None, env: Any) -> None:
    """Copy the weights of ``path`` into ``model`` after checking they fit ``env``."""
    if not path:
        return
    from geonav.policy.checkpoint import check_compatible, load_checkpoint

    ckpt = load_checkpoint(path)
    check_compatible(ckpt.meta, env, path=ckpt.path)
    model.load_state_dict(ckpt.model_state)


def _engine_opts(rest: dict[str, Any]) -> dict[str, Any]:
    """Pop the trainer engine options (engine, batch, device) from a stage's options, and
    ``pack`` (the runner's: it groups the seeds, see :func:`execute_group`)."""
    rest.pop("pack", None)
    return {"engine": rest.pop("engine", "batched"), "batch": rest.pop("batch", None),
            "device": rest.pop("device", None)}


def _where(p: dict[str, Any]) -> str:
    """How messages name a payload's stage: its TOML table."""
    return f"[stages.{p.get('stage')}]"


def _algo_cfg(p: dict[str, Any], obs_size_px: int | None = None
              ) -> tuple[Any, Any, dict[str, Any]]:
    """(base config, NetConfig or None, remaining options) from a payload's options;
    ``obs_size_px`` (else read from the payload's task set) fills a [net] that lacks it."""
    from geonav.policy.config import NetConfig, from_dict
    from geonav.policy.meta_config import BASE_CONFIGS, base_config

    opts = dict(p["options"])
    net_opts = {k: opts.pop(k) for k in list(opts) if k in NetConfig.__dataclass_fields__}
    if net_opts and "obs_size_px" not in net_opts:
        if obs_size_px is None:
            from geonav.tasks import TaskSet

            obs_size_px = TaskSet.load(p["tasks"]).camera.size_px
        net_opts["obs_size_px"] = obs_size_px
    fixed = {"episodes": p["episodes"], "workers": p["workers"], "seed": p["seed"]}
    if p["algo"] == "ppo":
        from geonav.policy.batched.ppo import PPOConfig

        ppo_opts = {k: opts.pop(k) for k in list(opts) if k in PPOConfig.__dataclass_fields__}
        cfg = from_dict(PPOConfig, {**ppo_opts, **fixed}, _where(p))
    else:
        known = BASE_CONFIGS[p["algo"]].__dataclass_fields__
        base_opts = {k: opts.pop(k) for k in list(opts) if k in known}
        cfg = base_config(p["algo"], {**base_opts, **fixed}, _where(p))
    return cfg, (from_dict(NetConfig, net_opts, _where(p)) if net_opts else None), opts


ENGINE_TYPES: dict[str, Any] = {"engine": str, "batch": int | None, "device": str | None,
                                "pack": bool}
"""The engine options of a stage (popped by :func:`_engine_opts`) and their types."""


def _meta_cfg(p: dict[str, Any], rest: dict[str, Any]) -> Any:
    """The MetaConfig of a meta-train unit from its remaining options (popped)."""
    from geonav.policy.config import from_dict
    from geonav.policy.meta_config import MetaConfig

    meta_opts = {k: rest.pop(k) for k in list(rest) if k in MetaConfig.__dataclass_fields__}
    if rest:
        raise ConfigError(f"stage {p.get('stage')!r}: unknown meta-train option(s) "
                          f"{sorted(rest)}")
    return from_dict(MetaConfig, {**meta_opts, "episodes": p["episodes"],
                                  "workers": p["workers"], "seed": p["seed"]}, _where(p))


def _curriculum_cfg(p: dict[str, Any], rest: dict[str, Any]) -> Any:
    """The CurriculumConfig of a curriculum unit from its remaining options (popped)."""
    from geonav.policy.config import from_dict
    from geonav.policy.meta_config import CurriculumConfig

    cur_opts = {k: rest.pop(k) for k in list(rest)
                if k in CurriculumConfig.__dataclass_fields__}
    if rest:
        raise ConfigError(f"stage {p.get('stage')!r}: unknown curriculum option(s) "
                          f"{sorted(rest)}")
    return from_dict(CurriculumConfig, {**cur_opts, "stage_episodes": p["episodes"]},
                     _where(p))


def check_stage(p: dict[str, Any], obs_size_px: int | None) -> None:
    """Build every config a unit of this payload would (nothing trains, no file is read),
    so an unknown option or a value of the wrong type or range is one ConfigError naming
    the stage and the field when the experiment config is read, not when the unit runs.

    Args:
        p: the payload's stage, mode, algo, episodes, workers, options and seed.
        obs_size_px: the camera of the stage's task set (fills a [net] that lacks it).
    """
    from geonav.configcheck import coerce

    opts = dict(p["options"])
    stage_augment(opts.pop("augment", None), p.get("stage"))
    for key in ("tensorboard", "stop_at_convergence"):
        if key in opts:
            coerce(bool, opts.pop(key), f"{_where(p)} {key}")
    for key, tp in ENGINE_TYPES.items():
        if key in opts:
            coerce(tp, opts[key], f"{_where(p)} {key}")
    if opts.get("engine", "batched") not in ("batched", "async"):
        raise ConfigError(f"{_where(p)} engine = {opts['engine']!r}: use 'batched' or 'async'")
    _, _, rest = _algo_cfg(dict(p, options=opts), obs_size_px)
    _engine_opts(rest)
    if p["mode"] == "train":
        _init_reset(p, rest)
    if p["mode"] == "meta-train":
        _meta_cfg(p, rest)
    elif p["mode"] == "curriculum":
        _curriculum_cfg(p, rest)
    elif rest:
        raise ConfigError(f"stage {p.get('stage')!r}: unknown {p['algo']} option(s) "
                          f"{sorted(rest)}")


def _init_net(p: dict[str, Any], net: Any, resume: str | None) -> Any:
    if resume is None and p.get("init_checkpoint"):
        from geonav.policy.checkpoint import load_checkpoint

        return load_checkpoint(p["init_checkpoint"]).net_config
    return net


def _train_trainer(p: dict[str, Any], env_factory: Any, callbacks: list[Any],
                   resume: str | None) -> Any:
    """The trainer of a train-mode unit, ready to train (init weights loaded)."""
    from geonav.policy.engine import build_trainer

    cfg, net, rest = _algo_cfg(p)
    eng = _engine_opts(rest)
    reset = _init_reset(p, rest)
    if rest:
        raise ConfigError(f"stage {p.get('stage')!r}: unknown {p['algo']} option(s) "
                          f"{sorted(rest)}")
    t = build_trainer(p["algo"], eng["engine"], env_factory, _init_net(p, net, resume), cfg,
                      batch=eng["batch"], device=eng["device"], out_dir=p["out_dir"],
                      resume=resume, callbacks=callbacks, tensorboard=False)
    if resume is None:
        _load_init(t.model, p.get("init_checkpoint"), t.env)
        if p.get("init_checkpoint") and reset != "none":
            t.model.reset_heads(reset)
    return t


def _init_reset(p: dict[str, Any], rest: dict[str, Any]) -> str:
    """A train stage's ``init_reset`` (popped): what of its ``init`` policy is drawn again
    before the fine-tune ('none', 'critic' or 'heads'; :meth:`ActorCritic.reset_heads`)."""
    from geonav.policy.model import INIT_RESETS

    value = rest.pop("init_reset", "none")
    if value not in INIT_RESETS:
        raise ConfigError(f"{_where(p)} init_reset = {value!r}: use one of {INIT_RESETS}")
    return str(value)


@trainer("train", "a3c", "savn", "isar", "ppo")
def _train_algo(p: dict[str, Any], env_factory: Any, callbacks: list[Any],
                resume: str | None) -> tuple[Any, int, str]:
    result = _train_trainer(p, env_factory, callbacks, resume).train()
    return result.model, result.episodes, str(result.checkpoint)


@trainer("meta-train", "a3c", "savn", "isar")
def _meta_train(p: dict[str, Any], env_factory: Any, callbacks: list[Any],
                resume: str | None) -> tuple[Any, int, str]:
    from geonav.policy.engine import build_meta_trainer

    cfg, net, rest = _algo_cfg(p)
    eng = _engine_opts(rest)
    meta = _meta_cfg(p, rest)
    t = build_meta_trainer(p["algo"], eng["engine"], env_factory, _init_net(p, net, resume),
                           cfg, meta, device=eng["device"], out_dir=p["out_dir"],
                           resume=resume, callbacks=callbacks, tensorboard=False)
    if resume is None:
        _load_init(t.model, p.get("init_checkpoint"), t.env)
    result = t.train()
    return result.model, result.episodes, str(result.checkpoint)


@trainer("curriculum", "isar", "a3c", "savn")
def _curriculum(p: dict[str, Any], env_factory: Any, callbacks: list[Any],
                resume: str | None) -> tuple[Any, int, str]:
    """The stages resume themselves from ``out_dir`` (curriculum.json and each stage's
    checkpoints/latest.pt); ``episodes`` is the budget of each stage."""
    from geonav.convergence import ConvergenceCriterion
    from geonav.policy.curriculum import run_curriculum

    cfg, net, rest = _algo_cfg(p)
    eng = _engine_opts(rest)
    cur = _curriculum_cfg(p, rest)
    conv = p.get("convergence") or {}
    criterion = ConvergenceCriterion(**{k: conv[k] for k in ("window", "threshold", "hold")
                                        if k in conv})
    res = run_curriculum(env_factory, p.get("init_checkpoint"), p["algo"], cfg, cur,
                         out_dir=p["out_dir"], criterion=criterion,
                         net_cfg=None if p.get("init_checkpoint") else net,
                         callbacks=callbacks, **eng)
    return res.model, res.episodes, str(res.checkpoint)


def execute_stage(p: dict[str, Any]) -> dict[str, Any]:
    """Run a unit (see the module docstring); returns the result recorded in result.json."""
    p, env_factory, callbacks, resume = prepare_unit(p)
    model, episodes, checkpoint = TRAINERS[(p["mode"], p["algo"])](p, env_factory, callbacks,
                                                                   resume)
    return unit_result(p, model, episodes, checkpoint)


def execute_group(payloads: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Run the units of a packed group (train-mode units of one stage, one per seed) as
    packed runs in this process (:mod:`geonav.policy.batched.packed`); each member keeps
    its own unit folder, resume and result exactly as :func:`execute_stage`. Members that
    cannot be packed are trained one after the other, with the reason logged."""
    from geonav.policy.batched.packed import packing_refusal, train_packed

    prepared = [prepare_unit(p) for p in payloads]
    for p, *_ in prepared:
        if p["mode"] != "train":
            raise ConfigError(f"stage {p['stage']!r}: pack = true applies to mode 'train' only")
    members = [_train_trainer(p, ef, cbs, resume) for p, ef, cbs, resume in prepared]
    reason = packing_refusal(members)
    if reason is None:
        results = train_packed(members)
    else:
        log.warning("stage %r: its seeds run one after the other, not packed: %s",
                    payloads[0]["stage"], reason)
        results = [m.train() for m in members]
    return [unit_result(p, r.model, r.episodes, str(r.checkpoint))
            for (p, *_), r in zip(prepared, results, strict=True)]


def prepare_unit(p: dict[str, Any]) -> tuple[dict[str, Any], Any, list[Any], str | None]:
    """Resume detection, metric truncation and callbacks of a unit: (payload, env
    factory, callbacks, resume checkpoint or None)."""
    import torch

    from geonav.policy.envs import EnvFactory

    torch.set_num_threads(1)
    key = (p["mode"], p["algo"])
    if key not in TRAINERS:
        known = sorted(f"{m}/{a}" for m, a in TRAINERS)
        raise ConfigError(f"stage {p['stage']!r}: mode {p['mode']!r} with algo {p['algo']!r} "
                          f"is not available; available: {known}")
    out = Path(p["out_dir"])
    latest = out / "checkpoints" / "latest.pt"
    resume = str(latest) if latest.exists() else None
    if resume is None and (out / "metrics.csv").exists():
        # killed before its first checkpoint: start the unit again from scratch
        for name in ("metrics.csv", "eval.csv", "config.json", "progress.json"):
            (out / name).unlink(missing_ok=True)
    if resume is not None:
        truncate_metrics(out / "metrics.csv", resume)
        truncate_metrics(out / "eval.csv", resume)  # before ConvergenceStop reads it
    p = dict(p, options=dict(p["options"]))
    augment = stage_augment(p["options"].pop("augment", None), p.get("stage"))
    # training sees the randomised imagery; every evaluation (unit_result) the clean one
    env_factory = EnvFactory(p["scene"], p["tasks"]) if augment is None else \
        EnvFactory(p["scene"], p["tasks"], augment=augment)
    callbacks: list[Any] = [ProgressFile(out / "progress.json")]
    if p["options"].pop("tensorboard", False):  # stage option: TensorBoard under SB3's tags
        from geonav.policy.callbacks import tensorboard_callback

        tb = tensorboard_callback(out / "tb", required=True)
        if tb is not None:
            callbacks.append(tb)
    stop = p["options"].pop("stop_at_convergence", False)
    if stop and int(p["options"].get("eval_every", -1)) == 0:
        raise ConfigError(f"stage {p.get('stage')!r}: stop_at_convergence needs the greedy "
                          "evaluations of both convergence rules; remove eval_every = 0")
    if stop and p["mode"] == "curriculum":
        log.warning("stage %r: stop_at_convergence does not apply to a curriculum unit (its "
                    "stages end on the criterion themselves)", p.get("stage"))
    if stop and p["mode"] != "curriculum":
        from geonav.convergence import ConvergenceCriterion
        from geonav.policy.callbacks import read_metrics

        before = [bool(r["success"]) for r in read_metrics(out / "metrics.csv")] \
            if resume is not None and (out / "metrics.csv").exists() else []
        evals_before = [(int(r["episode"]), float(r["greedy_sr"]))
                        for r in read_metrics(out / "eval.csv")] \
            if resume is not None and (out / "eval.csv").exists() else []
        crit = ConvergenceCriterion(**p["convergence"])
        callbacks.append(ConvergenceStop(crit, before, evals_before))
    return p, env_factory, callbacks, resume


def unit_result(p: dict[str, Any], model: Any, episodes: int, checkpoint: str
                ) -> dict[str, Any]:
    """The final evaluation (on the clean imagery) and the result.json record of a trained
    unit."""
    from geonav.policy.envs import EnvFactory

    out = Path(p["out_dir"])
    metrics, offset = out / "metrics.csv", 0
    eval_factory = EnvFactory(p["scene"], p["tasks"])
    evals = out / "eval.csv"
    if p["mode"] == "curriculum":
        # Convergence is judged on the last (lowest) stage; the earlier stages of the
        # unit count as episodes spent before it.
        stages = json.loads((out / "curriculum.json").read_text())["stages"]
        last = stages[-1]
        metrics = out / f"stage_{len(stages) - 1}_{float(last['alt_m']):g}m" / "metrics.csv"
        evals = metrics.with_name("eval.csv")
        offset = sum(int(s["episodes"]) for s in stages[:-1])
        eval_factory = EnvFactory(p["scene"], p["tasks"], alt_m=float(last["alt_m"]))
    evaluation, trajectories = evaluate_unit(model, checkpoint, eval_factory, p)
    return dict(stage=p["stage"], seed=p["seed"], mode=p["mode"], algo=p["algo"],
                episodes=int(episodes), episodes_before_metrics=offset, checkpoint=checkpoint,
                metrics=str(metrics), evals=str(evals), scene=p["scene"], tasks=p["tasks"],
                eval=evaluation, trajectories=trajectories)


def stage_augment(value: Any, stage: Any = None) -> Any:
    """A stage's ``augment`` option (a table of :class:`geonav.augment.AugmentConfig`
    fields) validated, or None when absent or false; ConfigError names the stage."""
    if value is None or value is False:
        return None
    from geonav.augment import AugmentConfig

    if value is True:
        return AugmentConfig()
    return AugmentConfig.from_dict(value, f"[stages.{stage}] augment")


def truncate_metrics(metrics_csv: Path, checkpoint: str) -> None:
    """Drop metric rows logged after ``checkpoint`` was written (they will be re-run)."""
    from geonav.policy.checkpoint import load_checkpoint

    if not metrics_csv.exists():
        return
    episodes = load_checkpoint(checkpoint).episodes
    lines = metrics_csv.read_text().splitlines(keepends=True)
    if not lines:
        return
    kept = [lines[0]] + [ln for ln in lines[1:] if ln.strip() and
                         int(float(ln.split(",", 1)[0])) <= episodes]
    if len(kept) != len(lines):
        tmp = metrics_csv.with_name(".metrics.tmp")
        tmp.write_text("".join(kept))
        os.replace(tmp, metrics_csv)
        log.info("resuming at episode %d: dropped %d metric rows logged after the checkpoint",
                 episodes, len(lines) - len(kept))


def evaluate_unit(model: Any, checkpoint: str, env_factory: Any, p: dict[str, Any]
                  ) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Final evaluation of a unit (ALGORITHMS.md (f)): greedy and sampled from every start
    cell (a held-out seeded sample above ``eval_starts``), the task's exact chance figures,
    the zero-shot figures of the policy the unit started from, and two greedy example
    trajectories."""
    from geonav.difficulty import env_difficulty
    from geonav.policy.agent import Agent
    from geonav.policy.checkpoint import load_checkpoint
    from geonav.policy.evaluation import evaluate_both

    env = env_factory()
    frozen = load_checkpoint(checkpoint).build_encoder()
    n_tasks = len(env.unwrapped.tasks)
    limit = int(p.get("eval_starts", 100))
    seed = 10_000 + int(p["seed"])  # held out: a seed no training worker uses
    res = evaluate_both(model, env, frozen=frozen, max_starts=limit, seed=seed)
    chance = env_difficulty(env)
    evaluation: dict[str, Any] = {
        "starts": res["starts"], **res["row"],
        "random_walk_sr": chance["random_walk_sr"], "blind_sr": chance["blind_sr"],
        "mean_shortest_path": chance["mean_shortest_path"],
        # the keys of geonav <= 0.1 (sampled actions)
        "success_rate": res["row"]["sampled_sr"], "spl": res["row"]["sampled_spl"]}
    if p.get("init_checkpoint"):
        init = load_checkpoint(p["init_checkpoint"])
        zs = evaluate_both(init.build_model(), env, frozen=init.build_encoder(),
                           max_starts=limit, seed=seed)
        evaluation["zero_shot"] = zs["row"]
    trajectories = []
    agent = Agent(model.eval(), frozen, greedy=True, seed=0)
    for i in range(min(2, n_tasks * 2)):
        agent.reset()
        obs, info = env.reset(seed=20_000 + i, options={"task": i % n_tasks})
        cells, done = [list(info["cell"])], False
        while not done:
            obs, _, terminated, truncated, info = env.step(agent.act(obs, info))
            cells.append(list(info["cell"]))
            done = terminated or truncated
        trajectories.append(dict(task_index=i % n_tasks, cells=cells,
                                 success=bool(info["success"])))
    return evaluation, trajectories
