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
        """``info``: total episodes, start episode, workers, run folder."""

    def on_episode(self, record: dict[str, Any]) -> bool | None:
        """One finished episode (see ``METRIC_FIELDS``)."""
        return None

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
    """Per-episode scalars to TensorBoard (only when the ``tensorboard`` extra is installed)."""

    def __init__(self, log_dir: str | os.PathLike[str], window: int = 100) -> None:
        from torch.utils.tensorboard import SummaryWriter  # ImportError without tensorboard

        self.writer = SummaryWriter(str(log_dir))
        self.recent: deque[float] = deque(maxlen=window)

    def on_episode(self, record: dict[str, Any]) -> None:
        ep = int(record["episode"])
        self.recent.append(float(record["success"]))
        for key in ("return", "length", "spl", "collisions", "policy_loss", "value_loss",
                    "entropy"):
            if record.get(key) is not None:
                self.writer.add_scalar(f"episode/{key}", float(record[key]), ep)
        self.writer.add_scalar("episode/success_rate_ma", sum(self.recent) / len(self.recent),
                               ep)

    def on_train_end(self, result: Any) -> None:
        self.writer.close()


def tensorboard_callback(log_dir: str | os.PathLike[str]) -> Callback | None:
    """A :class:`TensorBoardMetrics`, or None (logged) when tensorboard is not installed."""
    try:
        return TensorBoardMetrics(log_dir)
    except ImportError:
        log.info("tensorboard is not installed (pip install 'geonav[tensorboard]'); "
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


def plot_learning_curve(metrics_csv: str | os.PathLike[str], out_png: str | os.PathLike[str],
                        window: int = 100) -> Path:
    """Success-rate moving average and return per episode, as a PNG (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    rows = sorted(read_metrics(metrics_csv), key=lambda r: r["episode"] or 0)
    ep = np.array([r["episode"] for r in rows], float)
    succ = np.array([r["success"] for r in rows], float)
    ret = np.array([r["return"] for r in rows], float)
    w = max(1, min(window, len(rows)))
    kernel = np.ones(w) / w
    sr = np.convolve(succ, kernel, mode="valid") if len(rows) else succ
    rma = np.convolve(ret, kernel, mode="valid") if len(rows) else ret
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    a1.plot(ep[w - 1:], sr)
    a1.set_ylabel(f"success rate (MA {w})")
    a1.set_ylim(-0.02, 1.02)
    a1.grid(alpha=0.3)
    a2.plot(ep, ret, alpha=0.25, lw=0.8, label="return")
    a2.plot(ep[w - 1:], rma, label=f"MA {w}")
    a2.set_ylabel("return")
    a2.set_xlabel("episode")
    a2.legend(loc="lower right")
    a2.grid(alpha=0.3)
    fig.tight_layout()
    out = Path(out_png)
    tmp = out.with_name(f".{out.name}.tmp.png")
    fig.savefig(tmp, dpi=100)
    plt.close(fig)
    os.replace(tmp, out)
    return out
