"""``geonav train`` and ``geonav eval``: thin argparse front ends over the policy library.

Wire into ``geonav/cli.py`` with ``geonav.policy.cli.add_parser(subparsers)``; each
subparser sets ``handler`` to its function (``run_train`` / ``run_eval``), which returns
an exit status and raises :class:`geonav.errors.GeonavError` on bad input. This
module imports torch only inside the handlers, so ``geonav --help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path
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

# EnvFactory lives in the library (experiments use it too); re-exported for the CLIs.
from geonav.policy.envs import EnvFactory  # noqa: E402,F401


def add_parser(subparsers: Any) -> None:
    """Register ``train`` and ``eval`` on an argparse subparsers object."""
    from geonav.policy.config import ENCODERS, A3CConfig, NetConfig, field_help

    nh, ah = field_help(NetConfig), field_help(A3CConfig)
    p = subparsers.add_parser("train", help="train a navigation policy (A3C, SAVN, ISAR, PPO)",
                              description="Train a policy on a scene's tasks. The run folder "
                              "gets config.json, metrics.csv, checkpoints/ and "
                              "learning_curve.png.")
    p.add_argument("--algo", default="a3c", choices=["a3c", "savn", "isar", "ppo"],
                   help="training algorithm (ppo: batched engine only)")
    p.add_argument("--scene", required=True, help="scene package folder")
    p.add_argument("--tasks", required=True, help="task set JSON")
    p.add_argument("--altitude", type=positive_float, default=None, metavar="M",
                   help="fly every task at this altitude in metres (default: the tasks')")
    p.add_argument("--episodes", type=positive_int, default=None, help=ah["episodes"])
    p.add_argument("--workers", type=nonneg_int, default=None, help=ah["workers"])
    p.add_argument("--out", required=True, metavar="RUN_DIR", help="run folder")
    p.add_argument("--resume", default=None, metavar="CKPT", help="continue from a checkpoint "
                   "(episode count, weights, optimiser and RNG state)")
    p.add_argument("--seed", type=seed_int, default=None, help=ah["seed"])
    p.add_argument("--obs-size", type=positive_int, default=None, metavar="PX",
                   help="observation side in pixels (default: the task set's camera)")
    p.add_argument("--encoder", choices=ENCODERS, default=None, help=nh["encoder"])
    p.add_argument("--encoder-weights", default=None, metavar="PATH", help=nh["encoder_weights"])
    p.add_argument("--prev-view-input", action="store_true", default=None,
                   help=nh.get("prev_view_input"))
    p.add_argument("--t-max", type=positive_int, default=None, help=ah["t_max"])
    p.add_argument("--lr", type=positive_float, default=None, help=ah["lr"])
    p.add_argument("--max-steps", type=positive_int, default=None, help="episode cap override")
    p.add_argument("--checkpoint-every", type=positive_int, default=None,
                   help=ah["checkpoint_every"])
    p.add_argument("--config", default=None, metavar="TOML",
                   help="TOML file with [net] and [a3c] tables; command-line options win")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    from geonav.policy.meta_cli import add_algo_args, add_engine_args, add_parsers

    add_algo_args(p)
    add_engine_args(p)
    p.set_defaults(handler=run_train)

    e = subparsers.add_parser("eval", help="evaluate a policy checkpoint",
                              description="Greedy and sampled success rate, SPL, length / "
                              "shortest path and collisions from every valid start cell of "
                              "every task (a seeded sample above --max-starts), beside the "
                              "task's exact random-walk success.")
    e.add_argument("checkpoint", metavar="CKPT", help="policy checkpoint (.pt)")
    e.add_argument("--scene", required=True, help="scene package folder")
    e.add_argument("--tasks", required=True, help="task set JSON")
    e.add_argument("--altitude", type=positive_float, default=None, metavar="M",
                   help="fly every task at this altitude (default: the tasks')")
    e.add_argument("--max-starts", type=positive_int, default=500, metavar="N",
                   help="evaluate at most N start cells in all (a seeded sample; default 500)")
    e.add_argument("--seed", type=seed_int, default=0, help="seed of the start sample and of "
                   "sampled actions")
    e.add_argument("--max-steps", type=positive_int, default=None, help="episode cap override")
    e.add_argument("--json", default=None, metavar="FILE", help="also write the results as JSON")
    e.add_argument("--force", action="store_true",
                   help="replace an existing --json file (only an evaluation geonav wrote)")
    e.add_argument("--no-progress", action="store_true", help="no progress bar")
    e.set_defaults(handler=run_eval)
    add_parsers(subparsers)


def resolve_train_configs(args: argparse.Namespace, table: str = "a3c",
                          cls: Any = None) -> tuple[Any, Any]:
    """(NetConfig, A3CConfig) from defaults, the TOML file and the command line (``table``
    and ``cls``: another A3CConfig subclass, e.g. ``[ppo]`` and PPOConfig)."""
    from geonav.policy.config import (
        A3CConfig,
        LossConfig,
        NetConfig,
        from_dict,
        step_budget_first,
    )

    cls = cls or A3CConfig
    toml = load_toml(getattr(args, "config", None))
    unknown = sorted(set(toml) - {"net", table})
    if unknown:
        raise ConfigError(f"unknown table(s) {unknown} in {args.config}; use [net] and "
                          f"[{table}]")
    net_d = dict(toml.get("net", {}))
    a3c_d = dict(toml.get(table, {}))
    for key, val in (("encoder", args.encoder), ("encoder_weights", args.encoder_weights),
                     ("obs_size_px", args.obs_size),
                     ("prev_view_input", getattr(args, "prev_view_input", None) or None)):
        if val is not None:
            net_d[key] = val
    for key, val in (("episodes", args.episodes), ("workers", args.workers),
                     ("seed", args.seed), ("t_max", args.t_max), ("lr", args.lr),
                     ("checkpoint_every", args.checkpoint_every),
                     ("total_steps", getattr(args, "total_steps", None))):
        if val is not None:
            a3c_d[key] = val
    if "loss" in a3c_d and not isinstance(a3c_d["loss"], dict):
        raise ConfigError(f"[{table}.loss] must be a table")
    if "loss" in a3c_d or cls is A3CConfig:
        a3c_d["loss"] = a3c_d.get("loss") or {}
    a3c = from_dict(cls, step_budget_first(a3c_d), f"[{table}]")
    if not isinstance(a3c.loss, LossConfig):
        raise ConfigError(f"invalid [{table}.loss] table")
    return from_dict(NetConfig, net_d, "[net]") if net_d else None, a3c


def run_train(args: argparse.Namespace) -> int:
    """Handler of ``geonav train``."""
    from geonav.policy.engine import build_trainer

    if args.algo not in ("a3c", "ppo"):
        from geonav.policy.meta_cli import run_train_algo

        return run_train_algo(args)
    if args.algo == "ppo":
        from geonav.policy.batched.ppo import PPOConfig

        net_cfg, a3c = resolve_train_configs(args, "ppo", PPOConfig)
    else:
        net_cfg, a3c = resolve_train_configs(args)
    obs = args.obs_size if args.obs_size is not None else (
        net_cfg.obs_size_px if net_cfg is not None else None)
    factory = EnvFactory(str(args.scene), str(args.tasks), args.altitude, obs,
                         args.max_steps)
    factory = replace(factory, augment=getattr(args, "augment", None))
    if net_cfg is not None and obs is None:  # take the task set camera's size
        net_cfg = replace(net_cfg, obs_size_px=int(factory().observation_space["image"].shape[0]))
    from geonav.policy.meta_cli import extra_callbacks, run_summary

    progress = TqdmProgress(args.no_progress)
    trainer = build_trainer(args.algo, args.engine, factory, net_cfg, a3c, batch=args.batch,
                            device=args.device, out_dir=args.out, resume=args.resume,
                            callbacks=[progress.callback, *extra_callbacks(args)])
    print(run_summary(trainer.train()))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    """Handler of ``geonav eval``: greedy, sampled and view-ablated greedy from every start,
    beside chance."""
    if args.max_starts < 1:
        raise ConfigError(f"--max-starts must be >= 1, got {args.max_starts}")
    if args.json:
        from geonav.outputs import check_replaceable, not_an_evaluation, output_lock

        with output_lock(args.json, "--json"):  # checked before the minutes of evaluation
            check_replaceable(args.json, "evaluation file", force=args.force,
                              why_not=not_an_evaluation)
            return _eval(args)
    return _eval(args)


def _eval(args: argparse.Namespace) -> int:
    from geonav.policy import evaluation

    summary, res = evaluation.evaluate_checkpoint(
        args.checkpoint, args.scene, args.tasks, alt_m=args.altitude,
        max_steps=args.max_steps, max_starts=args.max_starts, seed=args.seed)
    g, s = summary["greedy"], summary["sampled"]
    ablated = summary.get("ablated") or {}
    abl = f"{ablated['sr']:.3f}" if ablated.get("sr") is not None else "n/a"
    print(f"{res['starts']} starts: greedy SR {g['sr']:.3f} SPL {g['spl']:.3f} | sampled SR "
          f"{s['sr']:.3f} SPL {s['spl']:.3f} | view-ablated (current view replaced by "
          f"another cell's): SR {abl} | chance: random walk "
          f"{summary['random_walk_sr']:.3f}, best view-blind (knows the target, ignores the "
          f"view) {summary['blind_sr']:.3f}", file=sys.stderr)
    print(json.dumps(_no_nan(summary)))
    if args.json:
        out = Path(args.json)
        tmp = out.with_name(f".{out.name}.tmp")
        per = {name: res[name].episodes for name in ("greedy", "sampled", "ablated")
               if name in res}
        tmp.write_text(json.dumps(_no_nan({**summary, "per_episode": per}), indent=1))
        os.replace(tmp, out)
    return 0


def _no_nan(obj: Any) -> Any:
    """``obj`` with NaN floats (a length ratio without successes) as None: strict JSON."""
    if isinstance(obj, float) and obj != obj:
        return None
    if isinstance(obj, dict):
        return {k: _no_nan(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_no_nan(v) for v in obj]
    return obj


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry (``python -m geonav.policy.cli train ...``) for use before wiring."""
    from geonav.errors import GeonavError

    parser = argparse.ArgumentParser(prog="geonav-policy")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args))
    except GeonavError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
