"""The altitude curriculum (ALGORITHMS.md (e)).

Stages at ``levels_m`` (75, 45, 15 m by default) on the same lattice (the task set's
tasks ``.with_alt``), each starting from the previous stage's final policy (the first
from ``init``, weights only) and trained with the base algorithm (ISAR by default) with
T_max = 120. A stage ends when the convergence criterion of ALGORITHMS.md (f) holds on
its training episodes (:func:`geonav.convergence.episodes_to_convergence`)
or when its budget is spent. With the KL teacher (option A, default) a stage's
interaction losses gain lambda * KL(pi_T || pi_theta), pi_T being the previous stage's
frozen final policy fed the render at the same cell at the previous altitude, lambda
falling linearly from 1 to 0 over the first 25 % of the stage budget. With
``teacher='input'`` (option B) no teacher policy runs: the network's extra input slot
(``NetConfig.prev_view_input``, required from the first stage on, so the weights
transfer unchanged) gets the view at the same cell at the previous stage's altitude
in the stages that have a teacher, and is zero-filled in the others (ISAR and SAVN;
A3C is refused).

Run folder: ``stage_<i>_<alt>m/`` per stage (the trainer's own layout), plus
``curriculum.json`` (stages done, their episodes and checkpoints) and
``checkpoints/latest.pt`` / ``final.pt`` (copies of the newest stage checkpoint).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from geonav.errors import ConfigError
from geonav.policy.callbacks import Callback
from geonav.policy.config import A3CConfig, NetConfig, to_dict
from geonav.policy.meta_config import CurriculumConfig

log = logging.getLogger(__name__)


class ConvergenceStop(Callback):
    """Stops a stage once the convergence criterion holds on its training successes."""

    def __init__(self, criterion: Any, check_every: int = 1) -> None:
        self.criterion = criterion
        self.check_every = max(1, check_every)
        self.successes: list[bool] = []
        self.converged_at: int | None = None

    def on_episode(self, record: dict[str, Any]) -> bool:
        from geonav.convergence import episodes_to_convergence

        self.successes.append(bool(record["success"]))
        if len(self.successes) % self.check_every:
            return True
        res = episodes_to_convergence(self.successes, self.criterion)
        if not res.censored:
            self.converged_at = res.episodes
            return False
        return True


@dataclass
class StageResult:
    alt_m: float
    episodes: int
    checkpoint: str
    converged_at: int | None
    teacher: str | None
    """The KL teacher's checkpoint (option A), else None."""
    prev_view_alt_m: float | None = None
    """The altitude of the extra slot's view (option B), else None (zero-filled)."""


@dataclass
class CurriculumResult:
    model: Any
    stages: list[StageResult] = field(default_factory=list)
    checkpoint: str | None = None

    @property
    def episodes(self) -> int:
        return sum(s.episodes for s in self.stages)


def trainer_class(algo: str) -> type:
    from geonav.policy.a3c import A3CTrainer
    from geonav.policy.isar import ISARTrainer
    from geonav.policy.savn import SAVNTrainer

    classes = {"a3c": A3CTrainer, "isar": ISARTrainer, "savn": SAVNTrainer}
    if algo not in classes:
        raise ConfigError(f"curriculum algo must be one of {sorted(classes)}, not {algo!r}")
    return classes[algo]


def _check_input_teacher(algo: str, init: str | None, net_cfg: NetConfig | None,
                         engine: str = "batched") -> None:
    """teacher='input' needs ISAR or SAVN (or A3C on the batched engine) and a network with
    the extra slot from stage 0."""
    from geonav.policy.checkpoint import load_checkpoint

    if algo not in ("isar", "savn") and not (algo == "a3c" and engine == "batched"):
        raise ConfigError(f"curriculum teacher='input' (the extra input slot) is implemented "
                          f"for isar and savn on both engines and for a3c on engine = "
                          f"'batched', not {algo!r} on engine {engine!r}")
    fix = ("meta-train (or train) the starting policy with prev_view_input = true in the "
           "[net] table (geonav meta-train/train --prev-view-input), so the slot exists "
           "from stage 0")
    if init is not None:
        if not load_checkpoint(init).net_config.prev_view_input:
            raise ConfigError(f"curriculum teacher='input' needs an init checkpoint with the "
                              f"extra input slot, but {init} has none; {fix}")
    elif net_cfg is None or not net_cfg.prev_view_input:
        raise ConfigError("curriculum teacher='input' needs a network with the extra input "
                          "slot: set prev_view_input = true in the [net] table "
                          "(--prev-view-input)")


#: What a stage folder holds before its first checkpoint (all written by its trainer).
STAGE_FILES = ("config.json", "metrics.csv", "eval.csv", "checkpoints", "tb",
               "progress.json", "learning_curve.png")


def _remove_unstarted_stage(stage_dir: Path) -> None:
    """Remove a stage folder of a run killed before its first checkpoint, so the stage
    starts again; refuse one that holds anything a stage does not write."""
    foreign = sorted(p.name for p in stage_dir.iterdir() if p.name not in STAGE_FILES)
    if foreign:
        raise ConfigError(f"{stage_dir} holds files a curriculum stage does not write "
                          f"({', '.join(foreign[:5])}); move them away or choose another --out")
    shutil.rmtree(stage_dir)


def run_curriculum(env_factory: Any, init: str | None, algo: str, base_cfg: A3CConfig,
                   cfg: CurriculumConfig | None = None, *, out_dir: str | os.PathLike[str],
                   criterion: Any = None, net_cfg: NetConfig | None = None,
                   callbacks: Sequence[Callback] = (), mp_context: str | None = None,
                   engine: str = "batched", batch: int | None = None,
                   device: str | None = None) -> CurriculumResult:
    """Run (or resume) the curriculum.

    Args:
        env_factory: a :class:`geonav.policy.cli.EnvFactory` (a dataclass with ``alt_m``
            and ``max_steps``) over the task set; each stage replaces its altitude.
        init: the starting policy (e.g. the 300 m meta-policy), weights only; None starts
            from scratch.
        algo: 'isar' (default in the paper), 'a3c' or 'savn'.
        base_cfg: the algorithm's config; its ``episodes`` is replaced by the stage budget.
        cfg: levels, stage budget, T_max, teacher.
        out_dir: run folder (see the module docstring); an existing ``curriculum.json``
            is resumed.
        criterion: a :class:`geonav.convergence.ConvergenceCriterion`
            (default: its defaults).
        engine, batch, device: the trainer engine of every stage
            (:func:`geonav.policy.engine.build_trainer`; a stage the batched engine does
            not implement, e.g. one with the KL teacher, runs on the async engine).
    """
    from geonav.outputs import output_lock

    # Held through every stage: a second curriculum into this folder is refused at once
    # instead of taking a live stage folder for one killed before its first checkpoint.
    with output_lock(out_dir, "--out"):
        return _run_curriculum(env_factory, init, algo, base_cfg, cfg, out_dir=out_dir,
                               criterion=criterion, net_cfg=net_cfg, callbacks=callbacks,
                               mp_context=mp_context, engine=engine, batch=batch,
                               device=device)


def _warm_start(trainer: Any, checkpoint: str) -> None:
    """A new stage starts from the previous stage's (or the init's) weights, its auxiliary
    modules (SAVN's learned loss) included."""
    from geonav.policy.checkpoint import check_compatible, load_checkpoint

    ck = load_checkpoint(checkpoint)
    check_compatible(ck.meta, trainer.env, path=ck.path)
    trainer.model.load_state_dict(ck.model_state)
    if ck.extra:
        for name, m in trainer.aux.items():
            if name in ck.extra:
                m.load_state_dict(ck.extra[name])


def _record_stage(out: Path, state_path: Path, state: dict[str, Any],
                  checkpoint: Any) -> None:
    """A finished stage's checkpoint as the curriculum's latest/final, and curriculum.json,
    each replaced atomically."""
    for name in ("latest.pt", "final.pt"):
        shutil.copyfile(checkpoint, out / "checkpoints" / f".{name}.tmp")
        os.replace(out / "checkpoints" / f".{name}.tmp", out / "checkpoints" / name)
    tmp = state_path.with_name(".curriculum.json.tmp")
    tmp.write_text(json.dumps(state, indent=1))
    os.replace(tmp, state_path)


def _stage_teacher(cfg: CurriculumConfig, i: int, prev_ckpt: str | None,
                   prev_alt: float | None, env_factory: Any) -> tuple[Any, Any]:
    """Stage ``i``'s (KL teacher spec, previous-view spec), either or both None."""
    from geonav.policy.teacher import PrevViewSpec, TeacherSpec

    if not cfg.teacher_at(i):
        return None, None
    alt = float(cfg.levels_m[i])
    if prev_ckpt is None or prev_alt is None:
        raise ConfigError(f"stage {i} ({alt:g} m) needs a teacher, but there is no "
                          "previous policy with a known altitude (pass init and "
                          "first_teacher_alt_m, or teacher_levels_m without it)")
    prev_factory = replace(env_factory, alt_m=float(prev_alt))
    if cfg.teacher == "input":
        return None, PrevViewSpec(prev_factory, float(prev_alt))
    return TeacherSpec(str(prev_ckpt), prev_factory, cfg.stage_episodes,
                       cfg.teacher_decay_fraction, cfg.teacher_weight, cfg.teacher_schedule,
                       cfg.teacher_loss, cfg.teacher_agree, cfg.teacher_mask), None


def _check_teacher_engine(cfg: CurriculumConfig, i: int, teacher: Any, trainer: Any) -> None:
    """The teacher variants beyond the paper's reading run on the batched engine only."""
    if teacher is not None and not teacher.is_paper and \
            trainer.engine_choice.engine != "batched":
        raise ConfigError(f"curriculum stage {i} ({cfg.levels_m[i]:g} m): teacher_schedule "
                          f"{cfg.teacher_schedule!r}, teacher_loss {cfg.teacher_loss!r}, "
                          f"teacher_mask {cfg.teacher_mask!r} and teacher_weight "
                          f"{cfg.teacher_weight:g} need the batched engine, but this stage "
                          f"runs on the async one ({trainer.engine_choice.reason}); for the "
                          "async engine set teacher_schedule 'linear' and teacher_mask "
                          "'none' (the paper's reading)")


def _run_curriculum(env_factory: Any, init: str | None, algo: str, base_cfg: A3CConfig,
                    cfg: CurriculumConfig | None, *, out_dir: str | os.PathLike[str],
                    criterion: Any, net_cfg: NetConfig | None, callbacks: Sequence[Callback],
                    mp_context: str | None, engine: str, batch: int | None,
                    device: str | None) -> CurriculumResult:
    """The body of :func:`run_curriculum`, under the lock of ``out_dir``."""
    from geonav.convergence import ConvergenceCriterion
    from geonav.policy.checkpoint import load_checkpoint
    from geonav.policy.engine import build_trainer

    cfg = cfg if cfg is not None else CurriculumConfig()
    criterion = criterion if criterion is not None else ConvergenceCriterion()
    out = Path(out_dir)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    state_path = out / "curriculum.json"
    state: dict[str, Any] = json.loads(state_path.read_text()) if state_path.exists() else {
        "stages": [], "init": init, "algo": algo, "curriculum": to_dict(cfg),
        "criterion": {"window": criterion.window, "threshold": criterion.threshold,
                      "hold": criterion.hold}, "base": to_dict(base_cfg)}
    trainer_class(algo)  # validates algo
    if cfg.teacher == "input":
        _check_input_teacher(algo, init, net_cfg, engine)
    prev_ckpt, prev_alt = init, cfg.first_teacher_alt_m
    model = None
    result = CurriculumResult(None)
    for s in state["stages"]:
        result.stages.append(StageResult(**s))
        prev_ckpt, prev_alt = s["checkpoint"], s["alt_m"]
    cap = cfg.max_steps if cfg.max_steps is not None else env_factory.max_steps
    for i in range(len(state["stages"]), len(cfg.levels_m)):
        alt = float(cfg.levels_m[i])
        factory = replace(env_factory, alt_m=alt, max_steps=cap)
        stage_dir = out / f"stage_{i}_{alt:g}m"
        latest = stage_dir / "checkpoints" / "latest.pt"
        resume = str(latest) if latest.exists() else None
        if resume is None and stage_dir.exists():
            _remove_unstarted_stage(stage_dir)  # killed before its first checkpoint
        teacher, prev_view = _stage_teacher(cfg, i, prev_ckpt, prev_alt,
                                            replace(env_factory, max_steps=cap))
        stop = ConvergenceStop(criterion)
        kwargs: dict[str, Any] = {"out_dir": stage_dir, "resume": resume,
                                  "callbacks": [stop, *callbacks], "mp_context": mp_context}
        if teacher is not None and algo == "a3c":
            # The A3C worker has no teacher hook: the stage runs without it, and says so.
            log.warning("curriculum stage %d (%g m): the KL teacher is implemented for isar "
                        "and savn only; this a3c stage runs without it", i, alt)
            state.setdefault("notes", []).append(f"stage {i}: a3c has no KL teacher")
            teacher = None
        if teacher is not None:
            kwargs["teacher"] = teacher
        if prev_view is not None:
            kwargs["prev_view"] = prev_view
        stage_net = net_cfg
        if resume is None and prev_ckpt is not None:
            stage_net = load_checkpoint(prev_ckpt).net_config
        trainer = build_trainer(algo, engine, factory, stage_net,
                                replace(base_cfg, episodes=cfg.stage_episodes), batch=batch,
                                device=device, **kwargs)
        _check_teacher_engine(cfg, i, teacher, trainer)
        if resume is None and prev_ckpt is not None:
            _warm_start(trainer, prev_ckpt)
        if resume is not None:  # the convergence window continues over the whole stage
            from geonav.policy.callbacks import read_metrics

            if (stage_dir / "metrics.csv").exists():
                stop.successes = [bool(r["success"]) for r in
                                  read_metrics(stage_dir / "metrics.csv")]
        res = trainer.train()
        model = res.model
        stage = StageResult(alt, res.episodes, str(res.checkpoint), stop.converged_at,
                            None if teacher is None else str(teacher.checkpoint),
                            None if prev_view is None else prev_view.alt_m)
        result.stages.append(stage)
        state["stages"].append(stage.__dict__)
        _record_stage(out, state_path, state, res.checkpoint)
        prev_ckpt, prev_alt = str(res.checkpoint), alt
        log.info("curriculum stage %d (%g m): %d episodes, converged at %s", i, alt,
                 res.episodes, stop.converged_at)
    if model is None:
        model = load_checkpoint(prev_ckpt).build_model() if prev_ckpt else None
    result.model = model
    result.checkpoint = str(out / "checkpoints" / "final.pt")
    return result
