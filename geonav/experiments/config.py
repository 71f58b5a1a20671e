"""Experiment configs: one TOML file describes scenes, task sets, stages and comparisons.

Layout (see ``configs/quick.toml``)::

    name = "quick"
    seeds = [0, 1, 2]

    [convergence]            # ALGORITHMS.md (f); identical for every method
    window = 100
    threshold = 0.95
    hold = 0.90

    [scenes.A]               # a synthetic kind, or path = "scenes/A"
    synthetic = "residential"
    size_m = 900.0

    [tasks.A_meta]           # made on the fly when absent (or path = "tasks.json")
    scene = "A"
    kind = "meta"            # meta: COUNT regions of SIZE m at ALT; scene: one per altitude
    count = 6

    [stages.meta]            # one training stage, run once per seed
    mode = "meta-train"      # train | meta-train | curriculum
    tasks = "A_meta"
    algo = "isar"
    episodes = 1500

    [stages.transfer]
    mode = "train"
    tasks = "B_target"
    init = "meta"            # starts from that stage's final policy (same seed)
    episodes = 1000

    [[compare]]              # one table/plot: methods are final stages
    name = "transfer vs scratch"
    part = "transfer"        # `--only transfer` runs just this comparison's stages
    methods = ["transfer", "scratch"]
    paper = { transfer = 2000, scratch = 50000 }

Every stage is a unit of work per seed; a stage with ``init`` waits for its
parent's unit of the same seed.
"""

from __future__ import annotations

import dataclasses
import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geonav.convergence import ConvergenceCriterion
from geonav.errors import ConfigError

STAGE_MODES = ("train", "meta-train", "curriculum")
ALGOS = ("a3c", "savn", "isar", "ppo")


@dataclass(frozen=True)
class SceneSpec:
    """A scene: a synthetic kind (made on the fly) or an existing scene package.

    Attributes:
        name: the key in the config.
        synthetic: "residential", "campus", "wild" or "mixed" (or None with ``path``).
        path: an existing scene package folder.
        size_m: synthetic scene side in metres.
        gsd_m: synthetic scene GSD in m/px.
        seed: synthetic generator seed.
    """

    name: str
    synthetic: str | None = None
    path: str | None = None
    size_m: float = 1200.0
    gsd_m: float = 0.25
    seed: int = 0


@dataclass(frozen=True)
class TaskSpec:
    """A task set: made from a scene on the fly, or loaded from ``path``.

    Attributes:
        name: the key in the config.
        scene: the scene key.
        path: an existing task set JSON (then the rest is ignored).
        kind: "meta" (``count`` regions of ``size_m`` at ``alt_m``) or "scene" (``alts_m``).
        count: number of meta-tasks.
        size_m: region side (meta) or centred square side (scene; None = whole scene).
        alt_m: meta-task altitude.
        alts_m: whole-scene altitudes.
        step_m: lattice step in metres.
        max_steps: episode cap.
        obs_size_px: camera image side.
        margin_alt_m: keep regions inside the imagery with this altitude's view margin.
        seed: sampler seed.
        fov_deg: camera field of view (degrees, square image).
        max_overlap: meta-task regions overlap each other by at most this area fraction.
        max_random_walk: keep only targets from which a uniform random walk succeeds at
            most this often (per task; None: any target). Issue 12 asks for 0.05.
        max_blind: keep only targets whose best view-blind policy (knows the target,
            ignores the view) succeeds at most this often, with start cells on every side
            of the target (per task; None: any target). 0.3 for a learning comparison
            that is to show navigation by the view (issue 29).
    """

    name: str
    scene: str
    path: str | None = None
    kind: str = "meta"
    count: int = 1
    size_m: float | None = 150.0
    alt_m: float = 300.0
    alts_m: tuple[float, ...] = (75.0, 45.0, 15.0)
    step_m: float = 15.0
    max_steps: int = 70
    obs_size_px: int = 84
    margin_alt_m: float | None = None
    seed: int = 0
    fov_deg: float = 90.0
    max_overlap: float = 0.5
    max_random_walk: float | None = None
    max_blind: float | None = None


@dataclass(frozen=True)
class StageSpec:
    """One training stage, run once per seed.

    Attributes:
        name: the key in the config.
        mode: "train" (one algorithm on a task set), "meta-train" (Eq. 1 over meta-tasks)
            or "curriculum" (altitude stages on a whole-scene task set).
        tasks: the task set key.
        algo: "a3c", "savn" or "isar".
        episodes: episode budget of the stage.
        init: a stage whose final policy this one starts from (same seed).
        init_alt_m: when ``init`` is a curriculum stage, start from its policy at this
            level (e.g. 45.0: the 45 m level's final policy) instead of its last level's.
        workers: worker processes inside the unit (0 = single process).
        options: algorithm options passed through (N, K, lr, encoder, ...), and the
            trainer engine: ``engine`` ("batched", the default, or "async"), ``batch``
            (slots of the batched engine, default 16) and ``device`` ("cpu" or "cuda").
            ``augment = {variants = 8, brightness = 0.2, contrast = 0.2, hue_deg = 15,
            blur_px = 1.0, gsd_jitter = 0.1, seed = 0}`` (or ``true`` for those
            defaults) trains on seeded imagery variants (:mod:`geonav.augment`); the
            unit's evaluations stay on the clean imagery.
    """

    name: str
    mode: str
    tasks: str
    algo: str = "isar"
    episodes: int = 1000
    init: str | None = None
    init_alt_m: float | None = None
    workers: int = 1
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CompareSpec:
    """A comparison between final stages.

    Attributes:
        name: title of the table and plots.
        part: the part name for ``--only`` (default: the name).
        methods: stage keys compared (episodes to convergence of each).
        paper: the paper's episodes to convergence per method, for the ratio column.
        count_parents: also report episodes including the stages each method starts from.
        claim: the claim it tests, as README's results table names it (default: the name),
            e.g. "5. transfer A -> B: 2K vs 50K episodes".
    """

    name: str
    methods: tuple[str, ...]
    part: str = ""
    paper: dict[str, float] = field(default_factory=dict)
    count_parents: bool = False
    claim: str = ""


BACKENDS = ("local", "ray")


@dataclass(frozen=True)
class BackendSpec:
    """Where the units run (``[backend]``; ``--backend``/``--address``/``--jobs`` override).

    Attributes:
        kind: "local" (spawned processes on this machine) or "ray" (Ray tasks).
        jobs: concurrent units (local: default 2 on the command line; ray: default the
            cluster's CPUs / cpus_per_unit).
        address: Ray cluster address: "auto", "ray://HOST:10001" or "HOST:6379".
        max_retries: times a unit whose worker died is rerun from its last checkpoint.
        cpus_per_unit: CPUs a Ray task reserves (default: max(1, the stage's workers)).
        gpus_per_unit: GPUs a Ray task reserves (fractions allowed).
    """

    kind: str = "local"
    jobs: int | None = None
    address: str | None = None
    max_retries: int = 2
    cpus_per_unit: float | None = None
    gpus_per_unit: float = 0.0


@dataclass(frozen=True)
class ExperimentConfig:
    """A whole experiment (see the module docstring)."""

    name: str
    seeds: tuple[int, ...]
    convergence: ConvergenceCriterion
    scenes: dict[str, SceneSpec]
    tasks: dict[str, TaskSpec]
    stages: dict[str, StageSpec]
    compare: tuple[CompareSpec, ...]
    eval_starts: int = 100
    flight: dict[str, Any] = field(default_factory=dict)
    source: str = ""
    backend: BackendSpec = field(default_factory=BackendSpec)

    def parts(self) -> list[str]:
        """The part names, in config order, each once (a part may hold several
        comparisons)."""
        return list(dict.fromkeys(c.part or c.name for c in self.compare))

    def stages_for(self, only: list[str] | None) -> list[str]:
        """Stage keys needed by the selected parts (all when ``only`` is None), parents first."""
        if not only:
            wanted = list(self.stages)
        else:
            unknown = sorted(set(only) - set(self.parts()))
            if unknown:
                raise ConfigError(f"--only {unknown}: unknown part(s); parts are {self.parts()}")
            wanted = [m for c in self.compare if (c.part or c.name) in only for m in c.methods]
        order: list[str] = []

        def visit(key: str) -> None:
            stage = self.stages[key]
            if stage.init:
                visit(stage.init)
            if key not in order:
                order.append(key)

        for key in wanted:
            visit(key)
        return order

    def to_dict(self) -> dict[str, Any]:
        return _jsonable(dataclasses.asdict(self))


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    return v


def _build(cls: type, name: str, d: Any, where: str) -> Any:
    """A spec dataclass from its TOML table, every value checked against the field's type
    (:mod:`geonav.configcheck`), so a wrong type is one line naming the table and key."""
    from geonav.configcheck import build

    if not isinstance(d, dict):
        raise ConfigError(f"{where} must be a table")
    known = {f.name for f in dataclasses.fields(cls)} - {"name"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; known: {sorted(known)}")
    try:
        return build(cls, d, where, name=name)
    except TypeError as err:  # a required key missing
        raise ConfigError(f"{where}: {err}") from err


#: Largest seed (a 32-bit unsigned integer, as every RNG geonav seeds accepts it).
MAX_SEED = 2**32 - 1


def parse_config(data: dict[str, Any], source: str = "") -> ExperimentConfig:
    """Validate a parsed TOML document into an :class:`ExperimentConfig`."""
    known = {"name", "seeds", "convergence", "scenes", "tasks", "stages", "compare",
             "eval_starts", "flight", "backend"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ConfigError(f"{source}: unknown top-level key(s) {unknown}; known: {sorted(known)}")
    for key in ("convergence", "scenes", "tasks", "stages", "flight"):
        if key in data and not isinstance(data[key], dict):
            raise ConfigError(f"{source}: [{key}] must be a table, got "
                              f"{type(data[key]).__name__} {data[key]!r}")
    for key in ("scenes", "tasks", "stages"):
        for name, value in data.get(key, {}).items():
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: [{key}.{name}] must be a table, got "
                                  f"{type(value).__name__} {value!r}")
    compare = data.get("compare", [])
    if not isinstance(compare, list) or not all(isinstance(c, dict) for c in compare):
        raise ConfigError(f"{source}: compare must be [[compare]] tables")
    from geonav.configcheck import coerce
    from geonav.convergence import convergence_criterion

    conv = convergence_criterion(data.get("convergence", {}), f"{source} [convergence]".strip())
    for key, tp in (("name", str), ("seeds", tuple[int, ...]), ("eval_starts", int)):
        if key in data:
            data = {**data, key: coerce(tp, data[key], f"{source} {key}".strip())}
    scenes = {k: _build(SceneSpec, k, v, f"[scenes.{k}]") for k, v in
              data.get("scenes", {}).items()}
    tasks = {k: _build(TaskSpec, k, v, f"[tasks.{k}]") for k, v in data.get("tasks", {}).items()}
    stages = {}
    for k, v in data.get("stages", {}).items():
        v = dict(v)
        options = {key: v.pop(key) for key in list(v) if key not in
                   {"mode", "tasks", "algo", "episodes", "init", "init_alt_m", "workers",
                    "options"}}
        v["options"] = {**v.get("options", {}), **options}
        stages[k] = _build(StageSpec, k, v, f"[stages.{k}]")
    compare = tuple(_build(CompareSpec, c.get("name", f"compare-{i}"),
                           {k: v for k, v in c.items() if k != "name"}, f"[[compare]] #{i}")
                    for i, c in enumerate(data.get("compare", [])))
    cfg = ExperimentConfig(
        name=str(data.get("name", Path(source).stem or "experiment")),
        seeds=tuple(int(s) for s in data.get("seeds", [0, 1, 2])),
        convergence=conv, scenes=scenes, tasks=tasks, stages=stages, compare=compare,
        eval_starts=int(data.get("eval_starts", 100)), flight=dict(data.get("flight", {})),
        source=source, backend=_backend(data.get("backend", {})),
    )
    _check(cfg)
    return cfg


def _backend(d: Any) -> BackendSpec:
    if isinstance(d, BackendSpec):
        return d
    if not isinstance(d, dict):
        raise ConfigError("[backend] must be a table")
    known = {f.name for f in dataclasses.fields(BackendSpec)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"[backend]: unknown key(s) {unknown}; known: {sorted(known)}")
    types: dict[str, tuple[type, ...]] = {
        "kind": (str,), "jobs": (int,), "address": (str,), "max_retries": (int,),
        "cpus_per_unit": (int, float), "gpus_per_unit": (int, float)}
    for key, value in d.items():
        if isinstance(value, bool) or not isinstance(value, types[key]):
            raise ConfigError(f"[backend] {key} = {value!r}: expected "
                              f"{' or '.join(t.__name__ for t in types[key])}")
    spec = BackendSpec(**d)
    if spec.kind not in BACKENDS:
        raise ConfigError(f"[backend] kind = {spec.kind!r}: use one of {BACKENDS}")
    if spec.max_retries < 0 or (spec.jobs is not None and spec.jobs < 0):
        raise ConfigError("[backend] max_retries and jobs must be >= 0")
    if spec.kind == "local" and spec.gpus_per_unit:
        raise ConfigError("[backend] gpus_per_unit needs kind = \"ray\" (local units use "
                          "whatever devices their stage options name)")
    return spec


def _check(cfg: ExperimentConfig) -> None:
    if not cfg.seeds:
        raise ConfigError("seeds must list at least one seed")
    bad = [s for s in cfg.seeds if not 0 <= s <= MAX_SEED]
    if bad:
        raise ConfigError(f"{cfg.source}: seeds {bad} must be within 0..{MAX_SEED}".strip(": "))
    if not cfg.stages:
        raise ConfigError(f"{cfg.source or 'the experiment'} defines no [stages.NAME] table: "
                          "nothing to run; see configs/quick.toml for a complete experiment")
    from geonav.tiles.synth import KINDS

    for s in cfg.scenes.values():
        if (s.synthetic is None) == (s.path is None):
            raise ConfigError(f"[scenes.{s.name}] needs exactly one of synthetic or path")
        if s.synthetic and s.synthetic not in KINDS:
            raise ConfigError(f"[scenes.{s.name}] synthetic = {s.synthetic!r}: use one of "
                              f"{', '.join(KINDS)}")
    for t in cfg.tasks.values():
        if t.scene not in cfg.scenes:
            raise ConfigError(f"[tasks.{t.name}] scene = {t.scene!r} is not among the scenes "
                              f"{sorted(cfg.scenes)}")
        if t.kind not in ("meta", "scene"):
            raise ConfigError(f"[tasks.{t.name}] kind = {t.kind!r}: use meta or scene")
    for st in cfg.stages.values():
        if st.mode not in STAGE_MODES:
            raise ConfigError(f"[stages.{st.name}] mode = {st.mode!r}: use one of {STAGE_MODES}")
        if st.algo not in ALGOS:
            raise ConfigError(f"[stages.{st.name}] algo = {st.algo!r}: use one of {ALGOS}")
        if st.tasks not in cfg.tasks:
            raise ConfigError(f"[stages.{st.name}] tasks = {st.tasks!r} is not among the task "
                              f"sets {sorted(cfg.tasks)}")
        if st.init is not None and st.init not in cfg.stages:
            raise ConfigError(f"[stages.{st.name}] init = {st.init!r} is not a stage")
        if st.episodes < 1:
            raise ConfigError(f"[stages.{st.name}] episodes must be >= 1")
        if st.init_alt_m is not None:
            _check_init_level(cfg, st)
        if st.options.get("init_reset", "none") != "none" and st.init is None:
            raise ConfigError(f"[stages.{st.name}] init_reset = "
                              f"{st.options['init_reset']!r} draws heads of the policy it "
                              "starts from, but the stage has no init")
        if st.options.get("augment") not in (None, False, True):
            from geonav.augment import AugmentConfig

            AugmentConfig.from_dict(st.options["augment"], f"[stages.{st.name}] augment")
        if "base_loss" in st.options:  # ISAR's base loss, checked before any unit runs
            _check_base_loss(st)
        _check_options(cfg, st)
    for key in cfg.stages:  # no cycles
        seen, cur = set(), key
        while cur is not None:
            if cur in seen:
                raise ConfigError(f"[stages.{key}] init chain has a cycle")
            seen.add(cur)
            cur = cfg.stages[cur].init
    for c in cfg.compare:
        missing = [m for m in c.methods if m not in cfg.stages]
        if missing:
            raise ConfigError(f"[[compare]] {c.name!r}: methods {missing} are not stages")
    check_noise(cfg)


def _check_init_level(cfg: ExperimentConfig, st: StageSpec) -> None:
    """``init_alt_m`` names a level of the curriculum stage ``init``."""
    from geonav.policy.meta_config import CurriculumConfig

    parent = cfg.stages.get(st.init) if st.init is not None else None
    if parent is None or parent.mode != "curriculum":
        raise ConfigError(f"[stages.{st.name}] init_alt_m needs init = a curriculum stage "
                          f"(init = {st.init!r})")
    levels = parent.options.get("levels_m",
                                CurriculumConfig.__dataclass_fields__["levels_m"].default)
    if float(st.init_alt_m) not in [float(a) for a in levels]:
        raise ConfigError(f"[stages.{st.name}] init_alt_m = {st.init_alt_m:g} is not a level "
                          f"of curriculum stage {parent.name!r} ({list(levels)} m)")


def _check_options(cfg: ExperimentConfig, st: StageSpec) -> None:
    """The stage's options built into the configs its units will use (unknown options, a
    value of the wrong type or out of range), before any unit runs."""
    from geonav.experiments.stages import TRAINERS, check_stage

    if (st.mode, st.algo) not in TRAINERS:
        known = sorted(f"{m}/{a}" for m, a in TRAINERS)
        raise ConfigError(f"[stages.{st.name}] mode {st.mode!r} with algo {st.algo!r} is not "
                          f"available; available: {known}")
    tspec = cfg.tasks[st.tasks]
    obs = tspec.obs_size_px
    if tspec.path and Path(tspec.path).exists():
        from geonav.tasks import TaskSet

        obs = TaskSet.load(tspec.path).camera.size_px
    check_stage(dict(stage=st.name, mode=st.mode, algo=st.algo, episodes=st.episodes,
                     workers=st.workers, options=dict(st.options), seed=cfg.seeds[0]), obs)


def _check_base_loss(st: StageSpec) -> None:
    from geonav.policy.meta_config import BASE_LOSSES

    value = st.options["base_loss"]
    if st.algo != "isar":
        raise ConfigError(f"[stages.{st.name}] base_loss is an ISAR option (algo = 'isar'), "
                          f"not {st.algo}'s")
    if value not in BASE_LOSSES:
        raise ConfigError(f"[stages.{st.name}] base_loss = {value!r}: use one of "
                          f"{BASE_LOSSES}")
    if value != "a3c" and st.mode != "train":
        raise ConfigError(f"[stages.{st.name}] base_loss = {value!r} is implemented for mode "
                          f"'train' (batched engine), not {st.mode!r}")


def check_noise(cfg: ExperimentConfig,
                chance: dict[str, float | dict[str, float]] | None = None) -> None:
    """Refuse a convergence rule that a policy which is not improving, or one that ignores
    the view, could meet (issues 10 and 29, ALGORITHMS.md (f)): (a) for each compared
    stage's budget, by seeded simulation of a stationary success stream at p = hold;
    (b) with ``chance`` (task-set key -> its chance figures: a dict with
    ``random_walk_sr`` and ``blind_sr``, or a bare random-walk SR), thresholds below the
    larger of the random walk and the best view-blind policy plus half the gap to 1."""
    from geonav.convergence import noise_check

    compared = {m for c in cfg.compare for m in c.methods}
    seen: set[tuple[int, float | None, float | None]] = set()
    for key in sorted(compared):
        st = cfg.stages[key]
        fig = None if chance is None else chance.get(st.tasks)
        if isinstance(fig, dict):
            rw, blind = fig.get("random_walk_sr"), fig.get("blind_sr")
        else:
            rw, blind = fig, None
        if (st.episodes, rw, blind) in seen:
            continue
        seen.add((st.episodes, rw, blind))
        reasons = noise_check(cfg.convergence, st.episodes, rw, blind_sr=blind)
        if reasons:
            raise ConfigError(f"[convergence] cannot tell learning from noise for stage "
                              f"{key!r} (tasks {st.tasks!r}, budget {st.episodes}): "
                              + "; ".join(reasons))


def read_toml(path: Path, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """A TOML config file's content, ``overrides`` replacing its top-level keys.

    Raises:
        ConfigError: the file does not exist or is not valid TOML.
    """
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError as err:
        raise ConfigError(f"config {path} does not exist") from err
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"config {path} is not valid TOML: {err}") from err
    data.update(overrides or {})
    return data


def load_config(path: str | Path, overrides: dict[str, Any] | None = None) -> ExperimentConfig:
    """Read a TOML experiment config; ``overrides`` replace top-level keys."""
    path = Path(path)
    return parse_config(read_toml(path, overrides), str(path))
