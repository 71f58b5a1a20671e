"""Episodes to convergence, defined once (ALGORITHMS.md (f)).

``SR_W(e)`` is the success rate over the last ``W`` completed training
episodes (pooled across workers, in completion order). The run has converged
at episode ``e*``, the first ``e >= W`` with ``SR_W(e) >= threshold`` such
that ``SR_W`` stays ``>= hold`` for the next ``W`` episodes. A run whose budget
ends before that is *censored* at its budget: we know only that
``e* > budget``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ConvergenceCriterion:
    """The convergence rule, identical across the methods compared.

    Attributes:
        window: W, episodes in the moving success rate (paper-scale default 500).
        threshold: SR_W that must be reached (0.95).
        hold: SR_W that must be kept for the next W episodes (0.90).
    """

    window: int = 500
    threshold: float = 0.95
    hold: float = 0.90

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ValueError(f"window must be >= 1, got {self.window}")
        if not 0.0 < self.hold <= self.threshold <= 1.0:
            raise ValueError(f"need 0 < hold <= threshold <= 1, got {self.hold}, "
                             f"{self.threshold}")


@dataclass(frozen=True)
class ConvergenceResult:
    """Episodes to convergence of one run.

    Attributes:
        episodes: e* (1-based count of completed episodes), or None when censored.
        budget: episodes the run completed.
        censored: True when the run never converged within its budget.
    """

    episodes: int | None
    budget: int

    @property
    def censored(self) -> bool:
        return self.episodes is None

    def value(self) -> float:
        """e*, or the budget for a censored run (a lower bound)."""
        return float(self.budget if self.episodes is None else self.episodes)


def moving_success_rate(success: Sequence[bool] | np.ndarray, window: int) -> np.ndarray:
    """SR over the last ``window`` episodes after each episode (NaN before ``window``)."""
    s = np.asarray(success, dtype=np.float64)
    out = np.full(len(s), np.nan)
    if len(s) >= window:
        c = np.concatenate([[0.0], np.cumsum(s)])
        out[window - 1:] = (c[window:] - c[:-window]) / window
    return out


def episodes_to_convergence(success: Sequence[bool] | np.ndarray,
                            criterion: ConvergenceCriterion = ConvergenceCriterion()
                            ) -> ConvergenceResult:
    """e* of a success sequence in completion order (see the module docstring)."""
    w = criterion.window
    sr = moving_success_rate(success, w)
    n = len(sr)
    # small epsilon: rates are multiples of 1/W and must compare exactly
    reach = np.nonzero(sr >= criterion.threshold - 1e-12)[0]
    below = sr < criterion.hold - 1e-12
    for i in reach:
        end = i + w
        if end >= n:
            break  # not enough episodes left to confirm the hold
        if not below[i + 1:end + 1].any():
            return ConvergenceResult(int(i + 1), n)
    return ConvergenceResult(None, n)


def summarize(results: Sequence[ConvergenceResult]) -> dict[str, float | int | None]:
    """Median and min-max over seeds; censored runs count at their budget (lower bounds).

    The median is reported as censored (a lower bound) when at least half of
    the runs are censored.
    """
    if not results:
        return dict(n=0, median=None, min=None, max=None, censored=0, median_censored=False)
    values = np.array([r.value() for r in results])
    censored = sum(r.censored for r in results)
    return dict(n=len(results), median=float(np.median(values)), min=float(values.min()),
                max=float(values.max()), censored=int(censored),
                median_censored=bool(censored * 2 >= len(results)))


def area_under_curve(success: Sequence[bool] | np.ndarray, window: int) -> float:
    """Mean of the moving success rate over the run (0..1): a threshold-free summary."""
    sr = moving_success_rate(success, min(window, max(1, len(success))))
    valid = sr[~np.isnan(sr)]
    return float(valid.mean()) if len(valid) else math.nan
