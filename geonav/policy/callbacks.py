"""Training callbacks: progress, per-episode CSV metrics, TensorBoard, learning curves.

The library never prints: the CLI turns :meth:`Callback.on_episode` into a tqdm bar.
"""

from __future__ import annotations

import csv
import logging
import os
from collections import deque
from pathlib import Path
from typing import Any

from geonav.errors import MissingExtra

log = logging.getLogger(__name__)

METRIC_FIELDS = ("episode", "worker", "task", "task_index", "return", "length", "success",
                 "spl", "collisions", "shortest_path", "policy_loss", "value_loss", "entropy",
                 "env_steps", "wall_s", "elapsed_s")
"""``wall_s``: the episode's own duration in its worker; ``elapsed_s``: seconds of training
since the run started (across resumes) when the episode was recorded."""


class Callback:
    """Hooks called by the trainers in the main process (all optional).

    ``on_episode`` may return False to stop training early.
    """

    def on_train_start(self, info: dict[str, Any]) -> None:
        """``info``: total episodes, start episode, workers, run folder, step budget, env
        steps so far, algorithm."""

    def on_episode(self, record: dict[str, Any]) -> bool | None:
        """One finished episode (see ``METRIC_FIELDS``)."""
        return None

    def on_update(self, stats: dict[str, Any]) -> None:
        """One optimiser update of the batched engine: its ``policy_loss``, ``value_loss``,
        ``entropy``, the update count ``n_updates`` and the run's ``env_steps`` so far
        (the async engine's updates happen in its workers and are not reported)."""

    def on_eval(self, row: dict[str, Any]) -> None:
        """A periodic greedy + sampled evaluation (``geonav.policy.evaluation.EVAL_FIELDS``)."""

    def on_checkpoint(self, path: Path, episodes: int) -> None:
        """A checkpoint was written."""

    def on_train_end(self, result: Any) -> None:
        """Training finished (``result`` is the trainer's result object)."""


class CSVMetrics(Callback):
    """Appends one row per episode to a CSV and flushes, so a crash loses nothing."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        new = not self.path.exists() or self.path.stat().st_size == 0
        self._f = open(self.path, "a", newline="")  # noqa: SIM115 - closed in on_train_end
        self._w = csv.DictWriter(self._f, fieldnames=METRIC_FIELDS, extrasaction="ignore")
        if new:
            self._w.writeheader()
            self._f.flush()

    def on_episode(self, record: dict[str, Any]) -> None:
        self._w.writerow({k: _fmt(record.get(k)) for k in METRIC_FIELDS})
        self._f.flush()

    def on_train_end(self, result: Any) -> None:
        self.close()

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()


def _fmt(v: Any) -> Any:
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


class TensorBoardMetrics(Callback):
    """Scalars to TensorBoard under Stable-Baselines3's tag names, x = cumulative env steps.

    So that a geonav run and an SB3 run on the same task overlay in one TensorBoard:

    * each run in its own sub-folder ``log_dir/<ALGO>_<N>`` (SB3's ``<tb_log_name>_<N>``:
      the next N for a new run, the latest for a resumed one), so two runs given the same
      folder are two runs, not one whose step axis jumps back;
    * ``rollout/ep_rew_mean``, ``rollout/ep_len_mean``, ``rollout/success_rate``: means
      over the last ``window`` episodes (SB3's ``stats_window_size``, 100), plus geonav's
      ``rollout/spl_mean`` and ``rollout/collisions_mean``;
    * ``train/value_loss``, ``train/entropy_loss`` (minus the mean entropy, SB3's sign)
      and the policy term as the SB3 algorithm of the same kind names it:
      ``train/policy_gradient_loss`` for PPO (SB3's PPO), ``train/policy_loss`` otherwise
      (SB3's A2C), plus ``train/n_updates``; once per optimiser update (:meth:`on_update`,
      the batched engine, as SB3 logs per update), else per episode (the async engine,
      whose updates happen in its workers);
    * ``eval/success_rate`` (and geonav's ``eval/spl``, ``eval/sampled_*``) from
      :meth:`on_eval`, as SB3's ``EvalCallback`` names them;
    * ``time/episodes``: episodes so far.

    The x-axis is the running total of env steps: the record's ``env_steps`` when it is a
    running total (it includes earlier runs after a resume), else the sum of the episode
    lengths this callback has seen. The event file is made when training starts (a run
    refused before that leaves none). Needs the ``tensorboard`` extra.

    Args:
        log_dir: the folder of the runs' sub-folders.
        window: episodes in the rollout means.
        name: the sub-folder's name before ``_N`` (default: the trainer's algorithm,
            upper case: ``A3C``, ``PPO``, ``META_ISAR``).
    """

    def __init__(self, log_dir: str | os.PathLike[str], window: int = 100,
                 name: str | None = None) -> None:
        import torch.utils.tensorboard  # noqa: F401 - ImportError now, without tensorboard

        self.log_dir = Path(log_dir)
        self.name = name
        self.writer: Any = None
        self.run_dir: Path | None = None
        self.algorithm: str | None = None
        self._per_update = False
        self.window = int(window)
        self.returns: deque[float] = deque(maxlen=window)
        self.lengths: deque[float] = deque(maxlen=window)
        self.successes: deque[float] = deque(maxlen=window)
        self.spls: deque[float] = deque(maxlen=window)
        self.collisions: deque[float] = deque(maxlen=window)
        self.env_steps = 0
        self.episodes = 0

    def on_train_start(self, info: dict[str, Any]) -> None:
        # A curriculum passes one callback to every stage: they share the first's run.
        if self.writer is None:
            self._open(str(info.get("algorithm") or ""), int(info.get("start_episode") or 0) > 0)
        self._per_update = bool(info.get("reports_updates")) or self._per_update

    def _open(self, algorithm: str, resume: bool) -> Any:
        from torch.utils.tensorboard import SummaryWriter

        self.algorithm = algorithm or None
        name = self.name or (algorithm or "geonav").upper().replace("-", "_")
        self.run_dir = run_folder(self.log_dir, name, resume)
        self.writer = SummaryWriter(str(self.run_dir))
        return self.writer

    def _w(self) -> Any:
        return self.writer if self.writer is not None else self._open("", False)

    def _train_tags(self, stats: dict[str, Any], x: int) -> None:
        policy_tag = "train/policy_gradient_loss" if self.algorithm == "ppo" \
            else "train/policy_loss"
        for tag, key, sign in ((policy_tag, "policy_loss", 1.0),
                               ("train/value_loss", "value_loss", 1.0),
                               ("train/entropy_loss", "entropy", -1.0)):
            if stats.get(key) is not None:
                self._w().add_scalar(tag, sign * float(stats[key]), x)

    def on_update(self, stats: dict[str, Any]) -> None:
        self._per_update = True
        x = max(int(stats.get("env_steps") or 0), self.env_steps)
        self._train_tags(stats, x)
        if stats.get("n_updates") is not None:
            self._w().add_scalar("train/n_updates", int(stats["n_updates"]), x)

    def _step(self, record: dict[str, Any]) -> int:
        self.env_steps += int(record.get("length") or 0)
        total = record.get("env_steps")
        if total is not None and int(total) > self.env_steps:  # a running total
            self.env_steps = int(total)
        return self.env_steps

    def on_episode(self, record: dict[str, Any]) -> None:
        x = self._step(record)
        self.episodes += 1
        for buf, key in ((self.returns, "return"), (self.lengths, "length"),
                         (self.successes, "success"), (self.spls, "spl"),
                         (self.collisions, "collisions")):
            if record.get(key) is not None:
                buf.append(float(record[key]))
        add = self._w().add_scalar
        for tag, buf in (("rollout/ep_rew_mean", self.returns),
                         ("rollout/ep_len_mean", self.lengths),
                         ("rollout/success_rate", self.successes),
                         ("rollout/spl_mean", self.spls),
                         ("rollout/collisions_mean", self.collisions)):
            if buf:
                add(tag, sum(buf) / len(buf), x)
        if not self._per_update:  # the async engine: the losses its episode's records hold
            self._train_tags(record, x)
        add("time/episodes", self.episodes, x)

    def on_eval(self, row: dict[str, Any]) -> None:
        """A periodic evaluation row (``geonav.policy.evaluation.EVAL_FIELDS``).

        The greedy policy's figures go under SB3's ``EvalCallback`` names (it evaluates
        deterministically by default): ``eval/success_rate``, plus ``eval/spl`` and
        ``eval/length_ratio``; the sampled policy's under ``eval/sampled_*``; the greedy
        policy's under view ablation (current view replaced by another cell's) under
        ``eval/ablated_success_rate`` and ``eval/ablated_spl``; and ``eval/mean_reward``,
        ``eval/mean_ep_length`` when the row has them.
        """
        # the run's total, or this callback's when it spans several runs (curriculum stages)
        x = max(int(row.get("env_steps") or 0), self.env_steps)
        for tag, key in (("eval/success_rate", "greedy_sr"), ("eval/spl", "greedy_spl"),
                         ("eval/length_ratio", "greedy_length_ratio"),
                         ("eval/collisions", "greedy_collisions"),
                         ("eval/sampled_success_rate", "sampled_sr"),
                         ("eval/sampled_spl", "sampled_spl"),
                         ("eval/ablated_success_rate", "ablated_sr"),
                         ("eval/ablated_spl", "ablated_spl"),
                         ("eval/mean_reward", "mean_reward"),
                         ("eval/mean_ep_length", "mean_ep_length")):
            value = row.get(key)
            if value is not None and value == value:  # NaN: nothing to plot
                self._w().add_scalar(tag, float(value), x)

    def on_train_end(self, result: Any) -> None:
        self.close()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()


def run_folder(log_dir: str | os.PathLike[str], name: str, resume: bool = False) -> Path:
    """SB3's run sub-folder ``log_dir/<name>_<N>``: N one above the largest there (1 for
    the first), or with ``resume`` the largest (a resumed run goes on in its folder; SB3's
    ``reset_num_timesteps=False``)."""
    import re

    base = Path(log_dir)
    pattern = re.compile(rf"^{re.escape(name)}_(\d+)$")
    ids = [int(m.group(1)) for p in (base.iterdir() if base.is_dir() else ())
           if p.is_dir() and (m := pattern.match(p.name))]
    latest = max(ids, default=0)
    return base / f"{name}_{latest if resume and latest else latest + 1}"


def tensorboard_callback(log_dir: str | os.PathLike[str], *, required: bool = False,
                         name: str | None = None) -> Callback | None:
    """A :class:`TensorBoardMetrics` writing to a run sub-folder of ``log_dir`` (for
    ``--tensorboard DIR``).

    TensorBoard logging is on only where a caller asks for it with a folder.

    Args:
        log_dir: the folder of the runs' sub-folders (``<ALGO>_<N>``).
        name: the sub-folder's name before ``_N`` (default: the algorithm).
        required: raise :class:`MissingExtra` when tensorboard is not installed (what an
            explicit ``--tensorboard`` should do); otherwise log a warning and return None.
    """
    try:
        return TensorBoardMetrics(log_dir, name=name)
    except ImportError as err:
        if required:
            raise MissingExtra("tensorboard", "tensorboard", "--tensorboard logging") from err
        log.warning("tensorboard is not installed (pip install 'geonav[tensorboard]'); "
                    "metrics go to the CSV only")
        return None


def read_metrics(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The rows of a metrics CSV, numbers parsed."""
    rows = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            out: dict[str, Any] = {}
            for k, v in row.items():
                try:
                    out[k] = float(v) if v not in ("", None) else None
                except ValueError:
                    out[k] = v
            rows.append(out)
    return rows


def curve_window(episodes: int, window: int | None = None) -> int:
    """Moving-average window for a run of ``episodes``: ``window`` if given, else a tenth
    of the run (1..500), never more than the run."""
    if window is None:
        window = min(500, max(1, round(episodes / 10)))
    return max(1, min(int(window), max(1, episodes)))


def running_env_steps(rows: list[dict[str, Any]]) -> Any:
    """Cumulative env steps at the end of each episode row (rows in episode order).

    The CSV's ``env_steps`` is used when it is a running total (non-decreasing, and at
    its end at least half the summed episode lengths: after a resume it also counts the
    earlier runs); otherwise the episode lengths are summed.
    """
    import numpy as np

    length = np.array([r.get("length") or 0.0 for r in rows], float)
    steps = np.array([np.nan if r.get("env_steps") is None else r["env_steps"] for r in rows],
                     float)
    summed = np.cumsum(length)
    if len(rows) and np.isfinite(steps).all() and (np.diff(steps) >= 0).all() \
            and steps[-1] >= 0.5 * summed[-1] and (len(rows) == 1 or steps[-1] > steps[0]):
        return steps
    return summed


def _trailing_mean(x: Any, w: int) -> Any:
    """Mean of the last ``w`` values at each index (fewer at the start: no empty head)."""
    import numpy as np

    c = np.concatenate([[0.0], np.cumsum(x)])
    i = np.arange(1, len(x) + 1)
    lo = np.maximum(0, i - w)
    return (c[i] - c[lo]) / (i - lo)


def plot_learning_curve(metrics_csv: str | os.PathLike[str], out_png: str | os.PathLike[str],
                        window: int | None = None) -> Path:
    """Success rate and return against episodes (bottom axis) and env steps (top axis).

    Args:
        metrics_csv: a metrics CSV (:data:`METRIC_FIELDS`).
        out_png: the PNG to write (atomically).
        window: moving-average window in episodes; default :func:`curve_window` (a
            tenth of the run), so a 50-episode run and a 50 000-episode run both show a
            curve. The first ``window - 1`` points average what there is so far.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = sorted(read_metrics(metrics_csv), key=lambda r: r["episode"] or 0)
    ep = np.array([r["episode"] for r in rows], float)
    succ = np.array([r["success"] for r in rows], float)
    ret = np.array([r["return"] for r in rows], float)
    steps = running_env_steps(rows)
    w = curve_window(len(rows), window)
    sr, rma = _trailing_mean(succ, w), _trailing_mean(ret, w)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 5.4), sharex=True)
    a1.plot(ep, sr)
    a1.set_ylabel(f"success rate (MA {w})")
    a1.set_ylim(-0.02, 1.02)
    a1.grid(alpha=0.3)
    if len(rows) > 1 and (np.diff(ep) > 0).all() and (np.diff(steps) > 0).all():
        top = a1.secondary_xaxis("top", functions=(lambda e: np.interp(e, ep, steps),
                                                   lambda s: np.interp(s, steps, ep)))
        top.set_xlabel("env steps")
    a2.plot(ep, ret, alpha=0.25, lw=0.8, label="return")
    a2.plot(ep, rma, label=f"MA {w}")
    a2.set_ylabel("return")
    total = f", {int(steps[-1]):,} env steps" if len(rows) else ""
    a2.set_xlabel(f"episode ({len(rows)} episodes{total})")
    a2.legend(loc="lower right")
    a2.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out_png)
    tmp = out.with_name(f".{out.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, out)
    return out
