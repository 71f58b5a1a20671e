"""What carries from 45 m to 15 m, and which higher-level query carries it (issue 31).

    python bench/altitude_carry.py                       # frozen random CNN, 5 variants
    python bench/altitude_carry.py --encoders corr --seeds 0
    python bench/altitude_carry.py --variants kl,ce-agree --episodes 4000 --json out.json

A two-altitude lab, small enough for 2 cores: ``--targets`` whole-scene tasks (one target
each, a 300 m square of the 450 m synthetic residential scene, 20 x 20 cells of 15 m, 60
steps, 64 px, view-blind <= 0.3 and random walk <= 0.1 at both altitudes) flown at 45 m
and 15 m on the same lattice. Per encoder, one teacher is trained at 45 m from scratch
(ISAR, batched engine, until the training-SR rule holds (W = 500, 0.95 / 0.90) or
``--teacher-episodes``; cached under bench/.cache/altitude). Then, per seed, a student at
15 m under each variant:

- ``scratch``: fresh weights, no teacher (the "standard agent");
- ``warm``: the teacher's weights, no teacher term;
- ``kl``: warm + lambda KL(pi_T || pi_theta), lambda 1 -> 0 over the first 25 % of the
  budget (the paper's reading, today's default);
- ``kl-agree``: the same term, lambda held at 1 until the student's greedy action equals
  the teacher's on 90 % of its acting steps, then falling;
- ``ce-agree``: DAgger-style distillation: the cross-entropy of the teacher's greedy action
  on the student's own states, held the same way;
- ``kl-w5``: the paper's schedule with lambda starting at 5;
- ``kl-mask``, ``kl-mask-agree``, ``ce-mask-agree``: the teacher's distribution
  renormalised over the moves possible at the student's cell at 15 m (a cell blocked at
  15 m but free at 45 m gets probability 0), with the paper's schedule or held until
  agreement (``kl-mask-agree80``: until 80 %, not 90 %);
- ``input``: option B, no teacher term: the network's extra input slot gets the view at
  the same cell at 45 m (its own teacher, trained at 45 m with the slot zero-filled; as
  everywhere in geonav, evaluation zero-fills the slot).

Every ``--eval-every`` episodes the student is evaluated greedily from every start cell
of every target at 15 m, and, in lock-step along those same episodes, the teacher is fed
the render of the same cell at 45 m: the fraction of steps where the two greedy actions
agree. Each update's teacher term (lambda included, per slot, beside the policy loss),
lambda, the acting agreement and the KL per step come from the trainer's metrics. The
teacher's own figures: greedy SR at 45 m, and greedy SR when it drives at 15 m (it acts on
45 m renders of the 15 m episode's cells), which is the most a perfect imitation could
reach, and the same with its moves masked to those possible at 15 m.

The rule, fixed before the runs: episodes until the greedy SR from every start at 15 m is
>= ``--rule`` (0.9) at two evaluations in a row (the first of the two), capped at
``--episodes``; the median over seeds, with the range.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from geonav.policy.callbacks import Callback  # noqa: E402 (after the path above)

VARIANTS = {  # name: (warm start, teacher options or None)
    "scratch": (False, None),
    "warm": (True, None),
    "kl": (True, {}),
    "kl-agree": (True, {"schedule": "agree"}),
    "ce-agree": (True, {"schedule": "agree", "loss": "ce"}),
    "kl-w5": (True, {"weight0": 5.0}),
    "kl-mask": (True, {"mask": "feasible"}),
    "kl-mask-agree": (True, {"mask": "feasible", "schedule": "agree"}),
    "ce-mask-agree": (True, {"mask": "feasible", "schedule": "agree", "loss": "ce"}),
    "kl-mask-agree80": (True, {"mask": "feasible", "schedule": "agree", "agree": 0.8}),
    "input": (True, "input"),
}
HIGH, LOW = 45.0, 15.0


def lab_tasks(cache: Path, targets: int, size_m: float) -> tuple[str, str]:
    """(scene, task set at 15 m) of the lab, made once under ``cache``."""
    from geonav.camera import Camera
    from geonav.demo import ensure_scene
    from geonav.scene import Scene
    from geonav.tasks import TaskSet, whole_scene_tasks

    scene_dir = cache / "scene_residential2"
    ensure_scene(scene_dir, "residential2", "residential", 2, size_m + 150.0, 0.5)
    path = cache / f"lab-{targets}-{size_m:g}.json"
    if not path.exists():
        scene = Scene.open(scene_dir)
        tasks, seen, seed = [], set(), 0
        while len(tasks) < targets:
            ts = whole_scene_tasks(scene, (HIGH, LOW), step_m=15.0, max_steps=60, seed=seed,
                                   size_m=size_m, camera=Camera(64, 90.0),
                                   max_random_walk=0.1, max_blind=0.3)
            seed += 1
            low = [t for t in ts.tasks if t.alt_m == LOW][0]
            if low.target_cell in seen:
                continue
            seen.add(low.target_cell)
            tasks.append(replace(low, name=f"scene@15m#{len(tasks)}"))
        TaskSet(ts.scene_name, ts.scene_id, tasks, ts.camera, ts.meta).save(path)
    return str(scene_dir), str(path)


def view_table(env: Any, net_cfg: Any) -> Any:
    """The policy's input table of every (task, cell) view of ``env``: frozen features, or
    uint8 images for the trainable CNN."""
    import torch

    from geonav.policy.encoders import build_frozen_encoder
    from geonav.vecenv import LatticeVecEnv

    venv = LatticeVecEnv(env.unwrapped, 1)
    frozen = build_frozen_encoder(net_cfg)
    if frozen is None:
        return torch.from_numpy(venv.image_table())
    return venv.feature_table(frozen)


def lockstep(actor: Any, actor_table: Any, env: Any, other: Any = None,
             other_table: Any = None, mask: bool = False) -> dict[str, float]:
    """Greedy episodes of ``actor`` from every start of ``env`` (its views from
    ``actor_table``), all at once; with ``other``, that policy is stepped along the same
    cells on ``other_table`` (the same rows at another altitude) and the fraction of live
    steps where the two greedy actions agree is returned beside SR and SPL. ``mask``:
    the actor chooses among the moves possible at its cell only."""
    import torch

    from geonav.policy.evaluation import all_starts, spl
    from geonav.vecenv import LatticeVecEnv

    starts = all_starts(env)
    venv = LatticeVecEnv(env.unwrapped, len(starts))
    venv.reset(tasks=[t for t, _ in starts], starts=[c for _, c in starts])
    b = len(starts)
    active = np.ones(b, bool)
    succ, spls, same, steps = np.zeros(b), np.zeros(b), 0, 0
    with torch.inference_mode():
        tix = torch.from_numpy(venv.target_index)
        tgt = actor.features(actor_table[tix])
        state = actor.initial_state(b)
        if other is not None:
            otgt, ostate = other.features(other_table[tix]), other.initial_state(b)
        while active.any():
            rows = torch.from_numpy(venv.view_index)
            logits, _, state = actor(actor_table[rows].unsqueeze(0), tgt, state)
            if mask:
                logits = logits.masked_fill(~torch.from_numpy(venv.feasible_moves()), -1e9)
            a = logits[0].argmax(-1)
            if other is not None:
                ol, _, ostate = other(other_table[rows].unsqueeze(0), otgt, ostate)
                live = torch.from_numpy(active)
                same += int((ol[0].argmax(-1) == a)[live].sum())
                steps += int(live.sum())
            res = venv.step(a.numpy(), autoreset=False)
            for f in res.final:
                s = f["slot"]
                if active[s]:
                    active[s] = False
                    succ[s] = f["success"]
                    spls[s] = spl(f["success"], f["shortest_path"], f["length"])
    out = {"sr": float(succ.mean()), "spl": float(spls.mean())}
    if other is not None:
        out["agree"] = same / max(steps, 1)
    return out


class Probe(Callback):
    """A trainer callback: every ``every`` episodes, the student's greedy SR/SPL from every
    start at 15 m and its agreement with the teacher along those episodes; per update, the
    trainer's loss and teacher columns (averaged between evaluations)."""

    def __init__(self, trainer: Any, env15: Any, table15: Any, teacher: Any,
                 table45: Any, every: int, rule: float, log: Any) -> None:
        self.trainer, self.env15, self.table15 = trainer, env15, table15
        self.teacher, self.table45 = teacher, table45
        self.every, self.rule, self.log = every, rule, log
        self.episodes = 0
        self.updates: list[dict[str, float]] = []
        self.rows: list[dict[str, Any]] = []
        self.converged_at: int | None = None

    def on_update(self, stats: dict[str, Any]) -> None:
        self.updates.append({k: float(v) for k, v in stats.items()
                             if isinstance(v, (int, float))})

    def on_episode(self, record: dict[str, Any]) -> bool:
        self.episodes += 1
        if self.episodes % self.every:
            return True
        row = self.evaluate()
        self.rows.append(row)
        self.log(json.dumps(row))
        if len(self.rows) >= 2 and self.rows[-2]["sr"] >= self.rule and row["sr"] >= self.rule:
            self.converged_at = self.rows[-2]["episodes"]
            return False
        return True

    def evaluate(self) -> dict[str, Any]:
        model = self.trainer.model
        was = model.training
        model.eval()
        res = lockstep(model, self.table15, self.env15, self.teacher, self.table45)
        if was:
            model.train()
        ups, self.updates = self.updates, []
        keys = ("policy_loss", "value_loss", "teacher_loss", "kl_weight", "teacher_agree",
                "teacher_kl")
        mean = {k: float(np.nanmean([u[k] for u in ups if k in u]))
                for k in keys if any(k in u for u in ups)}
        return {"episodes": self.episodes, **res, **mean}


def train_teacher(cache: Path, factory: Any, net_cfg: Any, episodes: int, log: Any) -> str:
    """The 45 m teacher of an encoder (ISAR from scratch until the training-SR rule holds), cached
    (with ``prev_view_input``: the slot zero-filled, the starting point of variant input)."""
    from geonav.convergence import ConvergenceCriterion
    from geonav.policy.curriculum import ConvergenceStop
    from geonav.policy.engine import build_trainer
    from geonav.policy.meta_config import ISARConfig

    out = cache / f"teacher45-{net_cfg.encoder}{'-pv' if net_cfg.prev_view_input else ''}"
    final = out / "checkpoints" / "final.pt"
    if final.exists():
        return str(final)
    latest = out / "checkpoints" / "latest.pt"
    stop = ConvergenceStop(ConvergenceCriterion())
    t0 = time.perf_counter()
    trainer = build_trainer("isar", "batched", replace(factory, alt_m=HIGH), net_cfg,
                            ISARConfig(episodes=episodes, seed=0), batch=16, out_dir=out,
                            resume=str(latest) if latest.exists() else None, callbacks=[stop])
    res = trainer.train()
    log(f"teacher {net_cfg.encoder}: {res.episodes} episodes, converged at "
        f"{stop.converged_at}, {time.perf_counter() - t0:.0f} s")
    return str(res.checkpoint)


def run_student(cache: Path, factory: Any, net_cfg: Any, teacher_ckpt: str, variant: str,
                seed: int, episodes: int, every: int, rule: float, tables: dict[str, Any],
                teacher_model: Any, log: Any) -> dict[str, Any]:
    """One student at 15 m under ``variant``; its evaluation rows and episodes to the rule."""
    from geonav.policy.checkpoint import load_checkpoint
    from geonav.policy.curriculum import _warm_start
    from geonav.policy.engine import build_trainer
    from geonav.policy.meta_config import ISARConfig
    from geonav.policy.teacher import PrevViewSpec, TeacherSpec

    warm, topts = VARIANTS[variant]
    kwargs: dict[str, Any] = {}
    if topts == "input":
        teacher_ckpt = train_teacher(cache, factory, replace(net_cfg, prev_view_input=True),
                                     tables["teacher_episodes"], log)
        kwargs["prev_view"] = PrevViewSpec(replace(factory, alt_m=HIGH), HIGH)
    elif topts is not None:
        kwargs["teacher"] = TeacherSpec(teacher_ckpt, replace(factory, alt_m=HIGH), episodes,
                                        0.25, **topts)
    stage_net = load_checkpoint(teacher_ckpt).net_config if warm else net_cfg
    out = cache / "students" / f"{net_cfg.encoder}-{variant}-s{seed}-e{episodes}"
    if out.exists():
        import shutil

        shutil.rmtree(out)
    probe = Probe(None, tables["env15"], tables["t15"], teacher_model, tables["t45"],
                  every, rule, lambda m: log(f"  {variant} s{seed}: {m}"))
    trainer = build_trainer("isar", "batched", replace(factory, alt_m=LOW), stage_net,
                            ISARConfig(episodes=episodes, seed=seed), batch=16, out_dir=out,
                            callbacks=[probe], **kwargs)
    probe.trainer = trainer
    if warm:
        _warm_start(trainer, teacher_ckpt)
    first = probe.evaluate()  # before any update
    first["episodes"] = 0
    probe.rows.insert(0, first)
    log(f"  {variant} s{seed}: {json.dumps(first)}")
    t0 = time.perf_counter()
    trainer.train()
    return {"variant": variant, "seed": seed, "converged_at": probe.converged_at,
            "episodes": probe.episodes, "rows": probe.rows,
            "wall_s": time.perf_counter() - t0}


def summary(runs: list[dict[str, Any]], cap: int) -> str:
    """A table: per variant, episodes to the rule (median [range], censored at the cap as
    ">cap"), final greedy SR, and the agreement and teacher term at the first evaluation."""
    lines = ["| variant | episodes to the rule | reached | final greedy SR | final SPL | "
             "agreement at 0 / final | teacher term / policy loss, first evaluation |",
             "|---|---|---|---|---|---|---|"]
    for v in dict.fromkeys(r["variant"] for r in runs):
        rs = [r for r in runs if r["variant"] == v]
        eps = [r["converged_at"] if r["converged_at"] is not None else cap + 1 for r in rs]
        med = statistics.median(eps)

        def fmt(e: float) -> str:
            return f">{cap}" if e > cap else f"{e:g}"
        fin = [r["rows"][-1] for r in rs]
        first = [r["rows"][1] if len(r["rows"]) > 1 else r["rows"][0] for r in rs]
        ratio = [f.get("teacher_loss", 0.0) / max(abs(f.get("policy_loss", 0.0)), 1e-9)
                 for f in first]
        lines.append(
            f"| {v} | {fmt(med)} [{fmt(min(eps))}-{fmt(max(eps))}] | "
            f"{sum(r['converged_at'] is not None for r in rs)}/{len(rs)} | "
            f"{statistics.median(f['sr'] for f in fin):.2f} | "
            f"{statistics.median(f['spl'] for f in fin):.2f} | "
            f"{statistics.median(r['rows'][0]['agree'] for r in rs):.2f} / "
            f"{statistics.median(f['agree'] for f in fin):.2f} | "
            f"{statistics.median(ratio):.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--encoders", default="random", help="comma list: random, corr, cnn")
    p.add_argument("--variants", default="scratch,warm,kl,kl-agree,ce-agree",
                   help=f"comma list of {', '.join(VARIANTS)}")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--targets", type=int, default=4)
    p.add_argument("--size", type=float, default=300.0, help="task square side, m")
    p.add_argument("--episodes", type=int, default=6000, help="student budget (cap)")
    p.add_argument("--teacher-episodes", type=int, default=20000)
    p.add_argument("--eval-every", type=int, default=250)
    p.add_argument("--rule", type=float, default=0.9)
    p.add_argument("--cache", default=str(ROOT / "bench" / ".cache" / "altitude"))
    p.add_argument("--json", default=None, help="write every run's rows here")
    args = p.parse_args(argv)
    for v in args.variants.split(","):
        if v not in VARIANTS:
            p.error(f"unknown variant {v!r}; known: {', '.join(VARIANTS)}")
    import torch

    from geonav.policy.checkpoint import load_checkpoint
    from geonav.policy.config import NetConfig
    from geonav.policy.envs import EnvFactory

    torch.set_num_threads(1)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)

    def log(m: str) -> None:
        print(m, flush=True)

    scene, tasks = lab_tasks(cache, args.targets, args.size)
    factory = EnvFactory(scene, tasks)
    env15, env45 = replace(factory, alt_m=LOW)(), replace(factory, alt_m=HIGH)()
    report: dict[str, Any] = {"args": vars(args), "encoders": {}}
    for enc in args.encoders.split(","):
        net_cfg = NetConfig(encoder=enc, obs_size_px=64)
        teacher_ckpt = train_teacher(cache, factory, net_cfg, args.teacher_episodes, log)
        ck = load_checkpoint(teacher_ckpt)
        tmodel = ck.build_model().eval()
        t15, t45 = view_table(env15, ck.net_config), view_table(env45, ck.net_config)
        own = lockstep(tmodel, t45, env45)
        driven = lockstep(tmodel, t45, env15)
        masked = lockstep(tmodel, t45, env15, mask=True)
        log(f"{enc}: teacher greedy SR at 45 m {own['sr']:.3f} (SPL {own['spl']:.3f}); "
            f"driving at 15 m on 45 m renders {driven['sr']:.3f}, masked to the moves "
            f"possible at 15 m {masked['sr']:.3f}")
        tables = {"env15": env15, "t15": t15, "t45": t45,
                  "teacher_episodes": args.teacher_episodes}
        runs = []
        for seed in (int(s) for s in args.seeds.split(",")):
            for v in args.variants.split(","):
                runs.append(run_student(cache, factory, net_cfg, teacher_ckpt, v, seed,
                                        args.episodes, args.eval_every, args.rule, tables,
                                        tmodel, log))
                log(f"  {v} s{seed}: converged at {runs[-1]['converged_at']} "
                    f"({runs[-1]['wall_s']:.0f} s)")
                report["encoders"][enc] = {"teacher45": own, "teacher_driven15": driven,
                                           "teacher_masked15": masked, "runs": runs}
                if args.json:
                    Path(args.json).write_text(json.dumps(report, indent=1))
        print(f"\n{enc}: teacher 45 m SR {own['sr']:.2f}, driving at 15 m {driven['sr']:.2f}, "
              f"masked {masked['sr']:.2f}")
        print(summary(runs, args.episodes))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
