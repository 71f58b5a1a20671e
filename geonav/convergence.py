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
from typing import Any

import numpy as np


@dataclass(frozen=True)
class ConvergenceCriterion:
    """The convergence rule, identical across the methods compared.

    Attributes:
        window: W, episodes in the moving success rate (paper-scale default 500).
        threshold: SR_W that must be reached (0.95).
        hold: SR_W that must be kept for the next W episodes (0.90).
        eval_threshold: greedy SR over all starts that two consecutive periodic
            evaluations must reach for the evaluation e* (0.95; :func:`eval_convergence`).
    """

    window: int = 500
    threshold: float = 0.95
    hold: float = 0.90
    eval_threshold: float = 0.95

    def __post_init__(self) -> None:
        if self.window < 1:
            raise ValueError(f"window must be >= 1, got {self.window}")
        if not 0.0 < self.hold <= self.threshold <= 1.0:
            raise ValueError(f"need 0 < hold <= threshold <= 1, got {self.hold}, "
                             f"{self.threshold}")
        if not 0.0 < self.eval_threshold <= 1.0:
            raise ValueError(f"eval_threshold must lie in (0, 1], got {self.eval_threshold}")


def convergence_criterion(values: dict[str, Any],
                          where: str = "[convergence]") -> ConvergenceCriterion:
    """A :class:`ConvergenceCriterion` from a TOML table: unknown keys, values of the wrong
    type and values out of range are one ConfigError naming ``where`` and the field."""
    from geonav.configcheck import check_fields
    from geonav.errors import ConfigError

    if not isinstance(values, dict):
        raise ConfigError(f"{where} must be a table, got {type(values).__name__} {values!r}")
    checked = check_fields(ConvergenceCriterion, values, where)
    try:
        return ConvergenceCriterion(**checked)
    except ValueError as err:
        raise ConfigError(f"{where}: {err}") from err


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


def summarize(results: Sequence[ConvergenceResult | EvalConvergence]
              ) -> dict[str, float | int | None]:
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


# -- the evaluation criterion and the noise check (issue 10, ALGORITHMS.md (f)) ------------

@dataclass(frozen=True)
class EvalConvergence:
    """Evaluation e*: the first periodic evaluation whose greedy SR over all starts is
    ``>= threshold`` and stays so at the next evaluation.

    Attributes:
        episodes: the training episode of that evaluation, or None (censored).
        budget: episodes the run completed.
        evaluations: evaluations seen.
    """

    episodes: int | None
    budget: int
    evaluations: int = 0

    @property
    def censored(self) -> bool:
        return self.episodes is None

    def value(self) -> float:
        return float(self.budget if self.episodes is None else self.episodes)


def eval_convergence(episodes: Sequence[int] | np.ndarray,
                     greedy_sr: Sequence[float] | np.ndarray, budget: int,
                     threshold: float = 0.95) -> EvalConvergence:
    """:class:`EvalConvergence` from evaluation rows (training episode, greedy SR)."""
    ep = list(episodes)
    sr = list(greedy_sr)
    for i in range(len(sr) - 1):
        if sr[i] >= threshold - 1e-12 and sr[i + 1] >= threshold - 1e-12:
            return EvalConvergence(int(ep[i]), budget, len(sr))
    return EvalConvergence(None, budget, len(sr))


def stationary_pass_rate(criterion: ConvergenceCriterion, budget: int, p: float,
                         sims: int = 200, seed: int = 0) -> float:
    """Fraction of seeded stationary Bernoulli(p) success streams of ``budget`` episodes
    that meet ``criterion``: how often a policy that is *not improving* would "converge".
    """
    rng = np.random.default_rng(seed)
    w = criterion.window
    if budget < 2 * w:
        return 0.0
    hits = 0
    chunk = max(1, int(2e7 // max(budget, 1)))
    for start in range(0, sims, chunk):
        n = min(chunk, sims - start)
        s = rng.random((n, budget)) < p
        c = np.concatenate([np.zeros((n, 1)), np.cumsum(s, axis=1)], axis=1)
        sr = (c[:, w:] - c[:, :-w]) / w                        # (n, budget - w + 1)
        reach = sr >= criterion.threshold - 1e-12
        below = sr < criterion.hold - 1e-12
        m = sr.shape[1]
        # next index > i where SR falls below hold (m if never)
        idx = np.where(below, np.arange(m)[None, :], m)
        nxt = np.minimum.accumulate(idx[:, ::-1], axis=1)[:, ::-1]
        nxt_after = np.concatenate([nxt[:, 1:], np.full((n, 1), m)], axis=1)
        ok = reach & (np.arange(m)[None, :] + w < m) & (nxt_after > np.arange(m)[None, :] + w)
        hits += int(ok.any(axis=1).sum())
    return hits / sims


def noise_check(criterion: ConvergenceCriterion, budget: int,
                random_walk_sr: float | None = None, *, blind_sr: float | None = None,
                max_pass_rate: float = 0.05, sims: int = 200, seed: int = 0) -> list[str]:
    """Reasons a convergence rule could be met by a policy that is not improving, or by
    one that does not use the view.

    (a) a stationary success stream at p = ``hold`` meets the rule within ``budget``
    with probability >= ``max_pass_rate`` (seeded simulation); (b) ``threshold`` or
    ``eval_threshold`` is below the larger chance line of the task set, the random walk
    or the best view-blind policy (knows the target, ignores the current view), plus
    half its gap to 1. Empty when the rule is sound. A budget under 2 W, where the
    training-SR rule can never be met (the smoke configs of the tests), passes (b) too:
    such a run shows nothing either way.
    """
    reasons = []
    rate = stationary_pass_rate(criterion, budget, criterion.hold, sims, seed)
    if rate >= max_pass_rate:
        reasons.append(
            f"a policy that is not improving, succeeding at a constant rate p = hold = "
            f"{criterion.hold:g}, meets the rule (W = {criterion.window}, threshold "
            f"{criterion.threshold:g}, hold {criterion.hold:g}) within {budget} episodes in "
            f"{rate:.0%} of {sims} seeded simulations (limit {max_pass_rate:.0%}); widen the "
            "window, raise the hold or lower the budget")
    if (random_walk_sr is not None or blind_sr is not None) and budget >= 2 * criterion.window:
        rw = random_walk_sr if random_walk_sr is not None else 0.0
        blind = blind_sr if blind_sr is not None else 0.0
        chance = max(rw, blind)
        floor = chance + (1.0 - chance) / 2.0
        figures = ", ".join(
            f"{label} {v:.3f}" for label, v in
            (("random-walk success", random_walk_sr),
             ("best view-blind success (knows the target, ignores the view)", blind_sr))
            if v is not None)
        hint = ("use tasks that need the view (max_blind = 0.3: interior targets)"
                if blind >= rw else "use a harder task")
        for name, value in (("threshold", criterion.threshold),
                            ("eval_threshold", criterion.eval_threshold)):
            if value < floor - 1e-12:
                reasons.append(
                    f"{name} {value:g} is below the task set's chance ({figures}) plus half "
                    f"the gap to 1 ({floor:.3f}); raise it to at least {floor:.3f} or "
                    f"{hint}")
    return reasons
