"""Evaluation on a fixed, seeded set of start cells: success rate, SPL, length, collisions.

SPL (Anderson et al. 2018) = mean_i S_i * l_i / max(p_i, l_i), with l_i the BFS
shortest path from the start and p_i the steps taken.

View ablation (ALGORITHMS.md (f)): with ``ablate_view`` the policy is shown, at every
step, the view of a uniformly drawn lattice cell of the same task other than the one the
drone is in (target view, dynamics and scoring unchanged). A policy that navigates by the
view falls toward the view-blind line (:mod:`geonav.difficulty`); one that ignores the
view keeps its SR. The draws come from one numpy generator per start (the eval seed and
the start's index), so the per-episode and the lock-step paths show the same decoys.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from geonav.policy.agent import Agent, torch_threads
from geonav.policy.encoders import FrozenEncoder
from geonav.policy.model import ActorCritic

Start = tuple[int, tuple[int, int]]


class Actor(Protocol):
    def reset(self) -> None: ...

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any] | None = None) -> int: ...


def spl(success: bool, shortest_path: int, length: int) -> float:
    """S * l / max(p, l) for one episode."""
    if not success:
        return 0.0
    return float(shortest_path) / max(float(length), float(shortest_path), 1e-9)


def eval_starts(env: Any, per_task: int, seed: int = 0) -> list[Start]:
    """``per_task`` seeded start cells for every task of ``env`` (with replacement only
    when a task has fewer valid starts than asked for)."""
    u = env.unwrapped
    rng = np.random.default_rng(seed)
    out: list[Start] = []
    for ti in range(len(u.tasks)):
        cells = u.start_cells(ti)
        idx = rng.choice(len(cells), size=per_task, replace=per_task > len(cells))
        out.extend((ti, cells[int(i)]) for i in idx)
    return out


class RandomAgent:
    """Uniformly random actions (the baseline every learning test beats)."""

    def __init__(self, n_actions: int = 4, seed: int = 0) -> None:
        self.n_actions = n_actions
        self.rng = np.random.default_rng(seed)

    def reset(self) -> None:
        pass

    def act(self, obs: dict[str, np.ndarray], info: dict[str, Any] | None = None) -> int:
        return int(self.rng.integers(self.n_actions))


@dataclass
class EvalResult:
    """Aggregate and per-episode evaluation figures."""

    success_rate: float
    spl: float
    mean_length: float
    mean_collisions: float
    greedy: bool
    episodes: list[dict[str, Any]] = field(repr=False, default_factory=list)

    def summary(self) -> dict[str, float]:
        return {"success_rate": self.success_rate, "spl": self.spl,
                "mean_length": self.mean_length, "mean_collisions": self.mean_collisions,
                "episodes": float(len(self.episodes))}


_ABLATION_STREAM = 0x5EED_AB1A
"""Mixed into the view-ablation seeds, so the decoy draws are independent of the start
cells and sampled actions drawn from the same eval seed."""


def ablation_rng(seed: int, start_index: int) -> np.random.Generator:
    """The generator of the decoy cells of the ``start_index``-th start of an evaluation
    with ``seed`` (one uniform draw per observation, see :func:`decoy_index`)."""
    return np.random.default_rng([int(seed), _ABLATION_STREAM, int(start_index)])


def decoy_index(current: Any, n_cells: Any, u: Any) -> Any:
    """Uniform choice of a lattice cell other than the current one, by flat index.

    Args:
        current: flat index ``ix * ny + iy`` of the drone's cell (int or int array).
        n_cells: ``nx * ny`` cells of the task's lattice (>= 2; int or int array).
        u: a uniform draw in [0, 1) (float or float array).

    Returns:
        The flat index of the decoy cell (same shape as ``current``): uniform over the
        ``n_cells - 1`` other cells, free or blocked.
    """
    k = np.minimum(np.floor(np.asarray(u) * (np.asarray(n_cells) - 1)).astype(np.int64),
                   np.asarray(n_cells) - 2)
    return k + (k >= np.asarray(current))


def ablated_observation(env: Any, obs: dict[str, np.ndarray], info: dict[str, Any],
                        u: float) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """(obs, info) as the policy sees them under view ablation: the current image replaced
    by the view of a decoy cell (:func:`decoy_index` with the draw ``u`` in [0, 1)), the
    target image and every info field unchanged. The info gains ``view_cell``, the decoy
    (ix, iy), which a feature cache keys on (:func:`geonav.policy.encoders.cache_key`), so
    an encoder's cached features are the decoy's. The decoy is rendered from
    ``env.unwrapped`` (clean imagery, as evaluation uses)."""
    u_env = env.unwrapped
    ti = int(info["task_index"])
    nx, ny = u_env.task_maps[ti].lattice.shape
    cell = (int(info["cell"][0]), int(info["cell"][1]))
    flat = int(decoy_index(cell[0] * ny + cell[1], nx * ny, u))
    decoy = (flat // ny, flat % ny)
    return {**obs, "image": u_env.observation_at(ti, decoy)}, {**info, "view_cell": decoy}


def run_episode(actor: Actor, env: Any, task_index: int, start: tuple[int, int], *,
                ablate_view: bool = False, rng: np.random.Generator | None = None
                ) -> dict[str, Any]:
    """One episode from a given start; returns its record (actions included).

    Args:
        actor: the policy.
        env: the environment.
        task_index: the episode's task.
        start: its start cell (ix, iy).
        ablate_view: show the actor, at every step, the view of another cell of the task
            (:func:`ablated_observation`); the episode itself is unchanged.
        rng: the decoy draws' generator (None: :func:`ablation_rng` (0, 0)).
    """
    actor.reset()
    obs, info = env.reset(options={"task": task_index, "start_cell": start})
    if ablate_view and rng is None:
        rng = ablation_rng(0, 0)
    shortest = int(info["shortest_path"])
    ret, length, collisions, actions = 0.0, 0, 0, []
    done = False
    while not done:
        if rng is not None and ablate_view:
            a = actor.act(*ablated_observation(env, obs, info, float(rng.random())))
        else:
            a = actor.act(obs, info)
        actions.append(a)
        obs, r, terminated, truncated, info = env.step(a)
        ret += float(r)
        length += 1
        collisions += int(bool(info["collided"]))
        done = terminated or truncated
    success = bool(info["success"])
    return {"task": info["task"], "task_index": task_index, "start": list(start),
            "return": ret, "length": length, "success": success,
            "spl": spl(success, shortest, length), "collisions": collisions,
            "shortest_path": shortest, "actions": actions}


def evaluate(policy: ActorCritic | Actor, env: Any, *, frozen: FrozenEncoder | None = None,
             episodes_per_task: int = 20, seed: int = 0, greedy: bool = True,
             starts: list[Start] | None = None,
             progress: Callable[[int, int], None] | None = None,
             threads: int | None = 1, ablate_view: bool = False) -> EvalResult:
    """Run ``policy`` from fixed seeded starts.

    Args:
        policy: an :class:`ActorCritic` (wrapped in an :class:`Agent`) or any object with
            ``reset()`` and ``act(obs, info)``.
        env: the environment.
        frozen: the frozen encoder of an ActorCritic that takes features.
        episodes_per_task: starts per task (ignored when ``starts`` is given).
        seed: seed of the start cells and of sampled actions.
        greedy: argmax actions; False samples from the policy.
        starts: explicit (task_index, cell) starts.
        progress: called with (done, total) after each episode.
        threads: torch threads while evaluating (restored after; None leaves them).
        ablate_view: replace the current view by another cell's at every step (module
            docstring); the decoys of start i come from :func:`ablation_rng` (seed, i).
    """
    if isinstance(policy, ActorCritic):
        was_training = policy.training
        policy.eval()
        actor: Actor = Agent(policy, frozen, greedy=greedy, seed=seed)
    else:
        was_training, actor = False, policy
    starts = starts if starts is not None else eval_starts(env, episodes_per_task, seed)
    records = []
    with torch_threads(threads):
        for i, (ti, cell) in enumerate(starts):
            rng = ablation_rng(seed, i) if ablate_view else None
            records.append(run_episode(actor, env, ti, cell, ablate_view=ablate_view, rng=rng))
            if progress is not None:
                progress(i + 1, len(starts))
    if isinstance(policy, ActorCritic) and was_training:
        policy.train()
    n = max(len(records), 1)
    return EvalResult(
        success_rate=sum(r["success"] for r in records) / n,
        spl=sum(r["spl"] for r in records) / n,
        mean_length=sum(r["length"] for r in records) / n,
        mean_collisions=sum(r["collisions"] for r in records) / n,
        greedy=greedy, episodes=records)


def all_starts(env: Any, max_starts: int | None = None, seed: int = 0) -> list[Start]:
    """Every valid start cell of every task of ``env``, or a seeded sample of
    ``max_starts`` of them (without replacement) when there are more."""
    u = env.unwrapped
    out: list[Start] = [(ti, c) for ti in range(len(u.tasks)) for c in u.start_cells(ti)]
    if max_starts is not None and 0 < max_starts < len(out):
        rng = np.random.default_rng(seed)
        idx = sorted(rng.choice(len(out), size=max_starts, replace=False).tolist())
        out = [out[i] for i in idx]
    return out


def length_ratio(records: list[dict[str, Any]]) -> float:
    """Mean episode length over the BFS shortest path (successful episodes; NaN if none)."""
    r = [rec["length"] / max(rec["shortest_path"], 1) for rec in records if rec["success"]]
    return float(np.mean(r)) if r else float("nan")


EVAL_FIELDS = ("episode", "env_steps", "elapsed_s", "starts", "greedy_sr", "greedy_spl",
               "greedy_length_ratio", "greedy_collisions", "sampled_sr", "sampled_spl",
               "sampled_length_ratio", "sampled_collisions", "ablated_sr", "ablated_spl")
"""Columns of a run's ``eval.csv`` (one row per periodic evaluation). ``ablated_*``: the
greedy policy under view ablation (module docstring); files written before it lack them."""


def evaluate_both(policy: ActorCritic | Actor, env: Any, *,
                  frozen: FrozenEncoder | None = None, max_starts: int | None = 100,
                  seed: int = 0, threads: int | None = 1, ablate: bool = True
                  ) -> dict[str, Any]:
    """Greedy and sampled evaluation from every start cell, and the greedy one under view
    ablation (ALGORITHMS.md (f)); an :class:`ActorCritic` on a GeoNavEnv is evaluated in
    lock-step (:func:`evaluate_lockstep`).

    Args:
        ablate: also run the view-ablated greedy evaluation (False: skip it, and the
            result and row have no ``ablated`` entries).

    Returns:
        ``{"starts": n, "greedy": EvalResult, "sampled": EvalResult, "ablated":
        EvalResult, "row": {...}}`` where ``row`` holds the ``EVAL_FIELDS`` figures
        (without episode/time columns).
    """
    starts = all_starts(env, max_starts, seed)
    lockstep = isinstance(policy, ActorCritic) and hasattr(env.unwrapped, "task_maps")

    def run(greedy: bool, ablate_view: bool = False) -> EvalResult:
        if lockstep:
            assert isinstance(policy, ActorCritic)
            return evaluate_lockstep(policy, env, starts, frozen=frozen, greedy=greedy,
                                     seed=seed, threads=threads, ablate_view=ablate_view)
        return evaluate(policy, env, frozen=frozen, starts=starts, greedy=greedy, seed=seed,
                        threads=threads, ablate_view=ablate_view)

    out: dict[str, Any] = {"starts": len(starts), "greedy": run(True), "sampled": run(False)}
    row: dict[str, float] = {"starts": len(starts)}
    for name in ("greedy", "sampled"):
        res = out[name]
        row[f"{name}_sr"] = round(res.success_rate, 6)
        row[f"{name}_spl"] = round(res.spl, 6)
        row[f"{name}_length_ratio"] = round(length_ratio(res.episodes), 6)
        row[f"{name}_collisions"] = round(res.mean_collisions, 6)
    if ablate:
        out["ablated"] = res = run(True, ablate_view=True)
        row["ablated_sr"] = round(res.success_rate, 6)
        row["ablated_spl"] = round(res.spl, 6)
    out["row"] = row
    return out


# -- lock-step evaluation: every start at once (one batched forward per step) --------------

_TABLES: weakref.WeakKeyDictionary[Any, dict[Any, Any]] = weakref.WeakKeyDictionary()
"""Per env: its view tables (images, and features per frozen encoder), built once."""


def evaluate_checkpoint(checkpoint: str, scene: str, tasks: str, *,
                        alt_m: float | None = None, max_steps: int | None = None,
                        max_starts: int | None = None, seed: int = 0
                        ) -> tuple[dict[str, Any], dict[str, Any]]:
    """Greedy, sampled and view-ablated greedy evaluation of a checkpoint on a scene's task
    set, beside chance (``geonav eval``). Returns (summary, the :func:`evaluate_both`
    result): the summary has ``checkpoint``, ``starts``, ``greedy`` and ``sampled`` (sr,
    spl, length_ratio, collisions), ``ablated`` (sr, spl: the greedy policy shown another
    cell's view at every step), ``random_walk_sr``, ``blind_sr`` (the best view-blind
    policy) and ``mean_shortest_path``."""
    from geonav.difficulty import env_difficulty
    from geonav.policy.checkpoint import check_compatible, load_checkpoint
    from geonav.policy.envs import EnvFactory

    ckpt = load_checkpoint(checkpoint)
    env = EnvFactory(str(scene), str(tasks), alt_m, int(ckpt.meta["obs_size_px"]),
                     max_steps)()
    check_compatible(ckpt.meta, env, path=ckpt.path)
    res = evaluate_both(ckpt.build_model(), env, frozen=ckpt.build_encoder(),
                        max_starts=max_starts, seed=seed)
    chance = env_difficulty(env)
    row = res["row"]
    summary = {"checkpoint": str(ckpt.path), "starts": res["starts"],
               "greedy": {k[7:]: v for k, v in row.items() if k.startswith("greedy_")},
               "sampled": {k[8:]: v for k, v in row.items() if k.startswith("sampled_")},
               "ablated": {k[8:]: v for k, v in row.items() if k.startswith("ablated_")},
               "random_walk_sr": round(chance["random_walk_sr"], 6),
               "blind_sr": round(chance["blind_sr"], 6),
               "mean_shortest_path": round(chance["mean_shortest_path"], 3)}
    return summary, res


def _view_table(env: Any, frozen: FrozenEncoder | None) -> Any:
    import torch

    from geonav.vecenv import LatticeVecEnv

    u = env.unwrapped
    cache = _TABLES.setdefault(u, {})
    if "images" not in cache:
        cache["venv"] = LatticeVecEnv(u, 1)
        cache["images"] = torch.from_numpy(cache["venv"].image_table())
    if frozen is None:
        return cache["images"]
    key = id(frozen)
    if key not in cache:
        cache[key] = cache["venv"].feature_table(frozen)
    return cache[key]


def decoy_rows(venv: Any, u: np.ndarray) -> np.ndarray:
    """(B,) view-table rows of a decoy cell per slot of ``venv`` (view ablation): a cell of
    the slot's task other than its current one, uniform over the lattice by the draws
    ``u`` (B,) in [0, 1), under the slot's imagery variant. With the 'corr' encoder the
    feature rows are already combined with their own task's target, so a row of the same
    task is exactly "another view, the target kept"."""
    task = venv.task
    current = venv.cell[:, 0] * venv.ny[task] + venv.cell[:, 1]
    flat = decoy_index(current, venv.nx[task] * venv.ny[task], u)
    return venv.variant * venv.n_cells + venv.offsets[task] + flat


def evaluate_lockstep(model: ActorCritic, env: Any, starts: list[Start], *,
                      frozen: FrozenEncoder | None = None, greedy: bool = True,
                      seed: int = 0, threads: int | None = 1,
                      ablate_view: bool = False) -> EvalResult:
    """:func:`evaluate` of an :class:`ActorCritic` from ``starts``, all episodes stepped
    together through :class:`geonav.vecenv.LatticeVecEnv` (GeoNavEnv's exact semantics)
    with one batched forward per step. Greedy results equal :func:`evaluate`'s; sampled
    actions come from one seeded torch generator, so they are a different (equally
    valid) draw. The previous-view slot is zero-filled, as in :func:`evaluate`.

    With ``ablate_view`` the network is fed, at every step, the row of a decoy cell
    (:func:`decoy_rows`) drawn with the same per-start generators as :func:`evaluate`
    (:func:`ablation_rng`), so greedy ablated results equal :func:`evaluate`'s too."""
    import torch

    from geonav.vecenv import LatticeVecEnv

    if not starts:
        return EvalResult(float("nan"), float("nan"), float("nan"), float("nan"), greedy)
    was_training = model.training
    model.eval()
    table = _view_table(env, frozen)
    venv = LatticeVecEnv(env.unwrapped, len(starts))
    venv.reset(tasks=[ti for ti, _ in starts], starts=[c for _, c in starts])
    b = len(starts)
    records: list[dict[str, Any] | None] = [None] * b
    actions: list[list[int]] = [[] for _ in range(b)]
    gen = torch.Generator().manual_seed(int(seed))
    draws: np.ndarray | None = None
    if ablate_view:  # (B, T): one draw per observation; no episode sees more than T
        horizon = max(int(venv.max_steps[ti]) for ti, _ in starts)
        draws = np.stack([ablation_rng(seed, s).random(horizon) for s in range(b)])
    t = 0
    with torch_threads(threads), torch.inference_mode():
        target = model.features(table[torch.from_numpy(venv.target_index)])
        state = model.initial_state(b)
        active = np.ones(b, bool)
        while active.any():
            rows = venv.view_index if draws is None else decoy_rows(venv, draws[:, t])
            t += 1
            obs = table[torch.from_numpy(rows)].unsqueeze(0)   # (1, B, ...)
            logits, _, state = model(obs, target, state)
            if greedy:
                a = logits[0].argmax(-1)
            else:
                a = torch.multinomial(torch.softmax(logits[0], -1), 1, generator=gen)[:, 0]
            a_np = a.numpy()
            for s in np.nonzero(active)[0].tolist():
                actions[s].append(int(a_np[s]))
            res = venv.step(a_np, autoreset=False)
            for f in res.final:
                s = f["slot"]
                if not active[s]:
                    continue  # a finished slot keeps moving; only its first end counts
                active[s] = False
                ti, cell = starts[s]
                records[s] = {"task": f["task"], "task_index": ti, "start": list(cell),
                              "return": f["return"], "length": f["length"],
                              "success": f["success"],
                              "spl": spl(f["success"], f["shortest_path"], f["length"]),
                              "collisions": f["collisions"],
                              "shortest_path": f["shortest_path"], "actions": actions[s]}
    if was_training:
        model.train()
    recs = [r for r in records if r is not None]
    n = max(len(recs), 1)
    return EvalResult(
        success_rate=sum(r["success"] for r in recs) / n, spl=sum(r["spl"] for r in recs) / n,
        mean_length=sum(r["length"] for r in recs) / n,
        mean_collisions=sum(r["collisions"] for r in recs) / n, greedy=greedy, episodes=recs)
