"""``geonav train --algo savn|isar``, ``geonav meta-train`` and ``geonav curriculum``.

Registered by :func:`geonav.policy.cli.add_parser`; torch is imported inside the
handlers only. A TOML ``--config`` may hold ``[net]``, the algorithm's table
(``[a3c]``, ``[savn]`` or ``[isar]``), ``[meta]`` and ``[curriculum]``; command-line
options win. Run folders have the A3C layout (config.json, metrics.csv, checkpoints/,
learning_curve.png); a curriculum adds one such folder per stage and curriculum.json.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from typing import Any

from geonav.cliutil import (
    TqdmProgress,
    load_toml,
    nonneg_int,
    positive_float,
    positive_int,
    seed_int,
)
from geonav.errors import ConfigError
from geonav.policy.config import step_budget_first
from geonav.policy.envs import EnvFactory

ALGOS = ("a3c", "savn", "isar")


def add_algo_args(p: argparse.ArgumentParser) -> None:
    """Options of SAVN and ISAR (None: the config's default)."""
    g = p.add_argument_group("SAVN / ISAR")
    g.add_argument("--preset", choices=["savn-published", "savn-aligned"], default=None,
                   help="SAVN preset: k=6, G=4 (published) or k=5, no limit (aligned)")
    g.add_argument("--inner-lr", type=positive_float, default=None,
                   help="SAVN inner SGD lr (alpha)")
    g.add_argument("--alpha", type=positive_float, default=None, help="ISAR inner SGD lr of theta")
    g.add_argument("--n-steps", type=positive_int, default=None, help="ISAR N: steps per segment")
    g.add_argument("--k-segments", type=positive_int, default=None,
                   help="ISAR K: segments per window")
    g.add_argument("--first-order", action="store_true",
                   help="do not differentiate through the inner updates (default: second order)")
    g.add_argument("--gradient-path", choices=["recompute", "per-step"], default=None,
                   help="ISAR: batched recompute of each segment (default) or a graph per step")
    from geonav.policy.config import field_help
    from geonav.policy.meta_config import BASE_LOSSES, ISARConfig

    ih = field_help(ISARConfig)
    g.add_argument("--base-loss", choices=BASE_LOSSES, default=None,
                   help=f"ISAR: {ih['base_loss']} (default a3c)")
    g.add_argument("--clip-coef", type=positive_float, default=None,
                   help=f"ISAR: {ih['clip_coef']} (default {ISARConfig.clip_coef})")
    g.add_argument("--ppo-epochs", type=positive_int, default=None,
                   help=f"ISAR: {ih['ppo_epochs']} (default {ISARConfig.ppo_epochs})")


def _augment_arg(text: str) -> Any:
    from geonav.augment import parse_augment

    try:
        return parse_augment(text)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def add_engine_args(p: argparse.ArgumentParser) -> None:
    """``--engine``, ``--batch`` and ``--device`` (geonav.policy.engine)."""
    g = p.add_argument_group("engine")
    g.add_argument("--engine", choices=["batched", "async"], default="batched",
                   help="'batched': many episodes in lock-step in one process (default); "
                   "'async': the per-episode multi-process reference trainer")
    g.add_argument("--batch", type=positive_int, default=None, metavar="B",
                   help="batched engine: episodes stepped together (default 16)")
    g.add_argument("--device", choices=["cpu", "cuda"], default="cpu",
                   help="batched engine: torch device (cuda is refused without a GPU)")
    g.add_argument("--augment", type=_augment_arg, default=None, metavar="SPEC",
                   help="train on seeded imagery variants (geonav.augment): key=value pairs "
                   "such as 'variants=8,brightness=0.2,contrast=0.2,hue_deg=15,blur_px=1,"
                   "gsd_jitter=0.1,seed=0,keep_clean=true' or the same as a JSON object; "
                   "unnamed keys keep those defaults ('variants=8' alone uses them all); "
                   "evaluations stay on the clean imagery")
    b = p.add_argument_group("budget and logging")
    b.add_argument("--total-steps", type=positive_int, default=None, metavar="N",
                   help="env-step budget in total (resumed steps included; per stage for the "
                   "curriculum); training ends when it or the episode budget runs out")
    b.add_argument("--tensorboard", default=None, metavar="DIR",
                   help="also log to TensorBoard event files in DIR under SB3's tag names "
                   "(rollout/ep_rew_mean, rollout/success_rate, eval/..., train/...) against "
                   "env steps, so runs overlay with SB3's (needs geonav[tensorboard])")


def extra_callbacks(args: argparse.Namespace) -> list[Any]:
    """The callbacks the common options ask for (--tensorboard)."""
    if getattr(args, "tensorboard", None) is None:
        return []
    from geonav.policy.callbacks import tensorboard_callback

    tb = tensorboard_callback(args.tensorboard, required=True)
    return [tb] if tb is not None else []


def _toml(args: argparse.Namespace) -> dict[str, Any]:
    return load_toml(getattr(args, "config", None))


def base_cfg_from_args(args: argparse.Namespace, algo: str, toml: dict[str, Any]) -> Any:
    """The algorithm's config: defaults < TOML table < command line."""
    from geonav.policy.meta_config import base_config

    if algo not in ALGOS:
        raise ConfigError(f"--algo must be one of {ALGOS}, not {algo!r}")
    opts = dict(toml.get(algo, {}))
    for key, attr in (("episodes", "episodes"), ("workers", "workers"), ("seed", "seed"),
                      ("lr", "lr"), ("checkpoint_every", "checkpoint_every"),
                      ("t_max", "t_max"), ("total_steps", "total_steps")):
        v = getattr(args, attr, None)
        if v is not None:
            opts[key] = v
    if algo == "savn":
        for key, attr in (("preset", "preset"), ("inner_lr", "inner_lr")):
            if getattr(args, attr, None) is not None:
                opts[key] = getattr(args, attr)
    if algo == "isar":
        for key, attr in (("alpha", "alpha"), ("n_steps", "n_steps"),
                          ("k_segments", "k_segments"), ("gradient_path", "gradient_path"),
                          ("base_loss", "base_loss"), ("clip_coef", "clip_coef"),
                          ("ppo_epochs", "ppo_epochs")):
            if getattr(args, attr, None) is not None:
                opts[key] = getattr(args, attr)
    if getattr(args, "first_order", False) and algo != "a3c":
        opts["second_order"] = False
    return base_config(algo, step_budget_first(opts), f"[{algo}]")


def net_cfg_from_args(args: argparse.Namespace, toml: dict[str, Any], factory: Any) -> Any:
    from geonav.policy.config import NetConfig, from_dict

    net_d = dict(toml.get("net", {}))
    for key, val in (("encoder", getattr(args, "encoder", None)),
                     ("encoder_weights", getattr(args, "encoder_weights", None)),
                     ("obs_size_px", getattr(args, "obs_size", None)),
                     ("prev_view_input", getattr(args, "prev_view_input", None) or None)):
        if val is not None:
            net_d[key] = val
    if not net_d:
        return None
    net_d.setdefault("obs_size_px", int(factory().observation_space["image"].shape[0]))
    return from_dict(NetConfig, net_d, "[net]")


def _check_tables(toml: dict[str, Any], allowed: set[str], path: Any) -> None:
    unknown = sorted(set(toml) - allowed)
    if unknown:
        raise ConfigError(f"unknown table(s) {unknown} in {path}; use {sorted(allowed)}")


def run_summary(result: Any) -> str:
    """The closing line of a training command: this call's work and the run's totals, and
    the final greedy evaluation when there was one."""
    sr = [r["success"] for r in result.records[-100:]]
    new = result.episodes - result.start_episode
    total = f" ({result.episodes} in all)" if result.start_episode else ""
    text = (f"trained {new} episodes{total}, {result.env_steps} env steps, "
            f"{result.steps_per_s:.0f} steps/s; last-{min(len(sr), 100)} training success "
            f"{(sum(sr) / len(sr)) if sr else float('nan'):.2f}")
    evals = getattr(result, "evals", None)
    if evals:
        e = evals[-1]
        text += (f"; greedy SR {e['greedy_sr']:.2f} / SPL {e['greedy_spl']:.2f} from "
                 f"{e['starts']} starts (sampled {e['sampled_sr']:.2f})")
    return text + f"; checkpoint {result.checkpoint}"


_summary = run_summary


def run_train_algo(args: argparse.Namespace) -> int:
    """``geonav train --algo savn|isar``."""
    from geonav.policy.engine import build_trainer

    toml = _toml(args)
    _check_tables(toml, {"net", args.algo}, args.config)
    factory = EnvFactory(str(args.scene), str(args.tasks), args.altitude, args.obs_size,
                         args.max_steps)
    factory = replace(factory, augment=getattr(args, "augment", None))
    cfg = base_cfg_from_args(args, args.algo, toml)
    net = net_cfg_from_args(args, toml, factory)
    if net is not None and args.obs_size is None:
        factory = replace(factory, obs_size_px=net.obs_size_px)
    progress = TqdmProgress(args.no_progress)
    result = build_trainer(args.algo, args.engine, factory, net, cfg, batch=args.batch,
                           device=args.device, out_dir=args.out, resume=args.resume,
                           callbacks=[progress.callback, *extra_callbacks(args)]).train()
    print(_summary(result))
    return 0


def _common(p: argparse.ArgumentParser, algo_default: str) -> None:
    from geonav.policy.config import ENCODERS

    p.add_argument("--scene", required=True, help="scene package folder")
    p.add_argument("--tasks", required=True, help="task set JSON")
    p.add_argument("--algo", choices=ALGOS, default=algo_default, help="base algorithm")
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder")
    p.add_argument("--workers", type=nonneg_int, default=None, help="worker processes (0: one "
                   "process, deterministic)")
    p.add_argument("--seed", type=seed_int, default=None, help="seed")
    p.add_argument("--lr", type=positive_float, default=None,
                   help="the base algorithm's Adam lr (ISAR: beta)")
    p.add_argument("--obs-size", type=positive_int, default=None, metavar="PX",
                   help="observation side in pixels (default: the task set's camera)")
    p.add_argument("--encoder", choices=ENCODERS, default=None, help="image encoder")
    p.add_argument("--encoder-weights", default=None, metavar="PATH",
                   help="ResNet18 weights file")
    p.add_argument("--prev-view-input", action="store_true", default=None,
                   help="add the extra previous-altitude input slot E(o^prev) to the network "
                   "(needed by curriculum --teacher input; zero-filled where unused)")
    p.add_argument("--config", default=None, metavar="TOML", help="TOML with [net], the "
                   "algorithm's table, [meta] / [curriculum]; command-line options win")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_algo_args(p)
    add_engine_args(p)


def add_parsers(subparsers: Any) -> None:
    """Register ``meta-train`` and ``curriculum``."""
    m = subparsers.add_parser(
        "meta-train", help="meta-train a policy over meta-tasks (Eq. 1)",
        description="Batches of B meta-tasks in cyclic order; each runs E episodes of the "
        "base algorithm from psi; psi <- psi - eta * sum of the task gradients.")
    _common(m, "isar")
    m.add_argument("--episodes", type=positive_int, default=None, help="episodes over all tasks")
    m.add_argument("--batch-tasks", type=positive_int, default=None, help="B (default: workers)")
    m.add_argument("--episodes-per-task", type=positive_int, default=None, help="E (default 1)")
    m.add_argument("--meta-lr", type=positive_float, default=None, help="eta (default 1e-3)")
    m.add_argument("--meta-optimizer", choices=["sgd", "adam"], default=None,
                   help="meta update rule (default sgd)")
    m.add_argument("--altitude", type=positive_float, default=None, metavar="M",
                   help="fly every task at this altitude (default: the tasks')")
    m.add_argument("--max-steps", type=positive_int, default=None, help="episode cap override")
    m.add_argument("--checkpoint-every", type=positive_int, default=None, help="episodes")
    m.add_argument("--resume", default=None, metavar="CKPT", help="continue from a checkpoint")
    m.set_defaults(handler=run_meta_train, func=run_meta_train)

    c = subparsers.add_parser(
        "curriculum", help="fine-tune through altitude stages (75, 45, 15 m)",
        description="Stages on the same lattice, each from the previous stage's policy, "
        "advancing on the convergence criterion or the stage budget. Run the same command "
        "again with the same --out to resume.")
    _common(c, "isar")
    c.add_argument("--init", default=None, metavar="CKPT", help="starting policy (weights)")
    c.add_argument("--levels", default=None, help="altitudes in metres, e.g. 75,45,15")
    c.add_argument("--stage-episodes", type=positive_int, default=None, help="budget per stage")
    c.add_argument("--max-steps", type=positive_int, default=None,
                   help="T_max of every level (default: the task set's max_steps)")
    c.add_argument("--teacher", choices=["kl", "none", "input"], default=None,
                   help="KL prior to the previous stage (default), none, or 'input': the "
                   "previous-altitude view in the network's extra input slot (needs an "
                   "--init checkpoint trained with --prev-view-input)")
    c.add_argument("--teacher-levels", default=None,
                   help="stages that get the teacher (default: all after the first)")
    c.add_argument("--teacher-mask", choices=["none", "feasible"], default=None,
                   help="'feasible' (default): the teacher renormalised over the moves possible "
                   "at the student's cell and altitude (batched engine; docs/learning.md "
                   "§15); 'none': the paper's reading")
    c.add_argument("--teacher-schedule", choices=["linear", "agree"], default=None,
                   help="lambda held until the student agrees with the teacher, then 1 -> 0 "
                   "over a quarter of the stage (agree, default; batched engine), or 1 -> 0 "
                   "from the start (linear, the paper's reading)")
    c.add_argument("--teacher-agree", type=positive_float, default=None,
                   help="the agreement at which schedule 'agree' lets lambda fall (0.9)")
    c.add_argument("--teacher-loss", choices=["kl", "ce"], default=None,
                   help="KL to the teacher (default) or the cross-entropy of its greedy "
                   "action (ce; batched engine)")
    c.add_argument("--teacher-weight", type=positive_float, default=None,
                   help="lambda's starting value (1)")
    c.add_argument("--window", type=positive_int, default=None, help="convergence W (default 500)")
    c.add_argument("--threshold", type=positive_float, default=None, help="convergence SR (0.95)")
    c.add_argument("--hold", type=positive_float, default=None,
                   help="SR kept for W episodes (0.90)")
    c.set_defaults(handler=run_curriculum_cmd, func=run_curriculum_cmd)


def run_meta_train(args: argparse.Namespace) -> int:
    """Handler of ``geonav meta-train``."""
    from geonav.policy.config import from_dict
    from geonav.policy.engine import build_meta_trainer
    from geonav.policy.meta_config import MetaConfig

    toml = _toml(args)
    _check_tables(toml, {"net", args.algo, "meta"}, args.config)
    factory = EnvFactory(str(args.scene), str(args.tasks), args.altitude, args.obs_size,
                         args.max_steps)
    factory = replace(factory, augment=getattr(args, "augment", None))
    meta_d = dict(toml.get("meta", {}))
    for key, val in (("episodes", args.episodes), ("workers", args.workers),
                     ("seed", args.seed), ("batch_tasks", args.batch_tasks),
                     ("episodes_per_task", args.episodes_per_task),
                     ("meta_lr", args.meta_lr), ("meta_optimizer", args.meta_optimizer),
                     ("checkpoint_every", args.checkpoint_every)):
        if val is not None:
            meta_d[key] = val
    base = base_cfg_from_args(argparse.Namespace(**{**vars(args), "episodes": None,
                                                    "workers": None, "seed": None,
                                                    "checkpoint_every": None}),
                              args.algo, toml)
    meta = from_dict(MetaConfig, step_budget_first(meta_d, base.total_steps), "[meta]")
    net = net_cfg_from_args(args, toml, factory)
    if net is not None and args.obs_size is None:
        factory = replace(factory, obs_size_px=net.obs_size_px)
    progress = TqdmProgress(args.no_progress)
    result = build_meta_trainer(args.algo, args.engine, factory, net, base, meta,
                                device=args.device, out_dir=args.out, resume=args.resume,
                                callbacks=[progress.callback, *extra_callbacks(args)]).train()
    print(_summary(result))
    return 0


def _floats(text: str | None) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError as err:
        raise ConfigError(f"expected comma-separated altitudes in metres, got {text!r}") \
            from err


def run_curriculum_cmd(args: argparse.Namespace) -> int:
    """Handler of ``geonav curriculum``."""
    from geonav.convergence import convergence_criterion
    from geonav.policy.config import from_dict
    from geonav.policy.curriculum import run_curriculum
    from geonav.policy.meta_config import CurriculumConfig

    toml = _toml(args)
    _check_tables(toml, {"net", args.algo, "curriculum", "convergence"}, args.config)
    cur_d = dict(toml.get("curriculum", {}))
    for key, val in (("levels_m", _floats(args.levels)), ("stage_episodes", args.stage_episodes),
                     ("max_steps", args.max_steps), ("teacher", args.teacher),
                     ("teacher_levels_m", _floats(args.teacher_levels)),
                     ("teacher_mask", args.teacher_mask),
                     ("teacher_schedule", args.teacher_schedule),
                     ("teacher_agree", args.teacher_agree),
                     ("teacher_loss", args.teacher_loss),
                     ("teacher_weight", args.teacher_weight)):
        if val is not None:
            cur_d[key] = val
    cur = from_dict(CurriculumConfig, cur_d, "[curriculum]")
    conv = dict(toml.get("convergence", {}))
    for key, val in (("window", args.window), ("threshold", args.threshold),
                     ("hold", args.hold)):
        if val is not None:
            conv[key] = val
    criterion = convergence_criterion(conv, "[convergence]")
    factory = EnvFactory(str(args.scene), str(args.tasks), None, args.obs_size, None)
    factory = replace(factory, augment=getattr(args, "augment", None))
    base = base_cfg_from_args(argparse.Namespace(**{**vars(args), "episodes": None}),
                              args.algo, toml)
    net = None if args.init else net_cfg_from_args(args, toml, factory)
    if args.obs_size is None:
        if args.init:
            from geonav.policy.checkpoint import load_checkpoint

            factory = replace(factory, obs_size_px=int(load_checkpoint(args.init)
                                                       .meta["obs_size_px"]))
        elif net is not None:
            factory = replace(factory, obs_size_px=net.obs_size_px)
    progress = TqdmProgress(args.no_progress)
    res = run_curriculum(factory, args.init, args.algo, base, cur, out_dir=args.out,
                         criterion=criterion, net_cfg=net,
                         callbacks=[progress.callback, *extra_callbacks(args)],
                         engine=args.engine, batch=args.batch, device=args.device)
    for s in res.stages:
        print(f"stage {s.alt_m:g} m: {s.episodes} episodes, converged at "
              f"{s.converged_at if s.converged_at is not None else 'never (budget)'}")
    print(f"final checkpoint {res.checkpoint}")
    return 0
