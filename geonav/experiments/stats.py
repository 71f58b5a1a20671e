"""Statistics over seeds as RL reviewers expect them (Agarwal et al., NeurIPS 2021).

:func:`seed_summary` gives, for one quantity measured once per seed (episodes to
convergence, final success rate, ...), the median with its min-max, the
interquartile mean (IQM: the mean of the middle 50 % of runs, robust to one
outlier seed yet using more runs than the median) and percentile
stratified-bootstrap confidence intervals for both. The interval estimates come
from the ``rliable`` library (``pip install 'geonav[stats]'``), not from code of
our own.

Censored runs (those that never converged and so report their budget, a lower
bound of the true value) are explicit: each value comes with a ``censored``
flag. They enter every statistic at their budget, and the summary says which
statistics are therefore lower bounds: a censored value changes a rank statistic
only if it sits at or below the ranks that statistic uses (its true value can
only be larger, moving it up in the order).
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np

from geonav.errors import ConfigError, MissingExtra

log = logging.getLogger(__name__)

IQM_CUT = 0.25
"""Fraction cut from each end for the interquartile mean (scipy's ``trim_mean``)."""


def _trim(n: int) -> int:
    """Runs that :func:`scipy.stats.trim_mean` cuts from each end for the IQM."""
    return int(IQM_CUT * n)


def _lower_bound_flags(values: np.ndarray, censored: np.ndarray) -> dict[str, bool]:
    """Which statistics are lower bounds because of censored values (1-D inputs)."""
    n = len(values)
    # rank order; a censored value sorts after an observed equal one (its truth is >=)
    order = np.lexsort((censored, values))
    ranks = np.empty(n, int)
    ranks[order] = np.arange(n)
    cranks = ranks[censored]
    if not len(cranks):
        return dict(median_censored=False, iqm_censored=False, min_censored=False,
                    max_censored=False)
    return dict(
        median_censored=bool((cranks <= n // 2).any()),
        iqm_censored=bool((cranks < n - _trim(n)).any()),
        min_censored=bool((cranks == 0).any()),
        max_censored=True,
    )


def seed_summary(values: Sequence[float] | np.ndarray, censored: Sequence[bool] | np.ndarray,
                 *, confidence: float = 0.95, reps: int = 5000, seed: int = 0) -> dict[str, Any]:
    """Median [min-max], IQM and stratified-bootstrap CIs of one quantity over seeds.

    Args:
        values: one value per run, shape (runs,), or (runs, tasks) to stratify the
            bootstrap by task (runs are resampled within each task, as rliable does).
            A censored run holds its budget.
        censored: same shape as ``values``; True where the run is censored (never
            converged within its budget, so the true value is at least ``values``).
        confidence: size of the confidence intervals (0.95 = 95 %).
        reps: bootstrap resamples.
        seed: seed of the bootstrap's random state (the same inputs give the same CIs).

    Returns:
        ``n`` (runs x tasks values), ``n_censored``; ``median``, ``min``, ``max``,
        ``iqm``, ``mean``; ``median_ci`` and ``iqm_ci`` as ``[low, high]``; the flags
        ``median_censored``, ``iqm_censored``, ``min_censored``, ``max_censored``
        (True: the statistic, and its interval, are lower bounds); ``confidence``,
        ``reps`` and ``method``. With no runs every statistic is None; with one run
        the intervals are that value.

    Raises:
        ConfigError: shapes differ, a value is not finite, or ``confidence``/``reps``
            are out of range.
        MissingExtra: ``rliable`` is not installed (``pip install 'geonav[stats]'``).
    """
    x = np.asarray(values, dtype=float)
    c = np.asarray(censored, dtype=bool)
    if x.ndim == 1:
        x = x[:, None]
    if c.ndim == 1:
        c = c[:, None]
    if x.ndim != 2 or x.shape != c.shape:
        raise ConfigError(f"values {np.shape(values)} and censored {np.shape(censored)} must "
                          "have the same shape, (runs,) or (runs, tasks)")
    if not np.isfinite(x).all():
        raise ConfigError(f"values must be finite (a censored run holds its budget): {values}")
    if not 0.0 < confidence < 1.0:
        raise ConfigError(f"confidence must lie in (0, 1), got {confidence}")
    if reps < 100:
        raise ConfigError(f"reps must be >= 100 for a percentile interval, got {reps}")
    out: dict[str, Any] = dict(n=int(x.size), n_censored=int(c.sum()), confidence=confidence,
                               reps=reps, method="rliable stratified bootstrap, percentile")
    if x.size == 0:
        out.update(median=None, min=None, max=None, iqm=None, mean=None, median_ci=None,
                   iqm_ci=None, median_censored=False, iqm_censored=False,
                   min_censored=False, max_censored=False)
        return out
    try:
        from rliable import library as rly
        from rliable import metrics
    except ImportError as err:
        raise MissingExtra("rliable", "stats", "seed statistics (IQM, bootstrap CIs)") from err
    flat, cflat = x.ravel(), c.ravel()
    out.update(median=float(np.median(flat)), min=float(flat.min()), max=float(flat.max()),
               iqm=float(metrics.aggregate_iqm(x)), mean=float(flat.mean()),
               **_lower_bound_flags(flat, cflat))
    if x.shape[0] < 2:  # nothing to resample within a task
        out.update(median_ci=[out["median"], out["median"]], iqm_ci=[out["iqm"], out["iqm"]])
        return out

    def aggregate(scores: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_median(scores), metrics.aggregate_iqm(scores)])

    # rliable 1.2 draws its resamples from numpy's global generator (StratifiedBootstrap.
    # update_indices ignores random_state): seed it for the call, then restore the caller's
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            # rliable hands arch a RandomState; arch announces a future change of that API
            warnings.filterwarnings("ignore", "random_state is deprecated", FutureWarning)
            _, intervals = rly.get_interval_estimates(
                {"runs": x}, aggregate, method="percentile", reps=reps,
                confidence_interval_size=confidence, random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(saved)
    ci = intervals["runs"]  # (2 bounds, 2 statistics)
    out.update(median_ci=[float(ci[0, 0]), float(ci[1, 0])],
               iqm_ci=[float(ci[0, 1]), float(ci[1, 1])])
    return out


def format_summary(s: dict[str, Any], fmt: str = "{:.0f}") -> str:
    """One table cell: ``median [min-max], IQM x (CI lo-hi)``; ``+`` marks a lower bound."""
    if not s.get("n"):
        return "n/a"

    def v(key: str) -> str:
        value = s[key]
        text = fmt.format(value) if value is not None and math.isfinite(value) else "n/a"
        return text + ("+" if s.get(f"{key}_censored") else "")

    lo, hi = s["iqm_ci"]
    return (f"{v('median')} [{v('min')}-{v('max')}], IQM {v('iqm')} "
            f"({int(round(100 * s['confidence']))}% CI {fmt.format(lo)}-{fmt.format(hi)})")
