import numpy as np
import pytest

from geonav.experiments.convergence import (
    ConvergenceCriterion,
    episodes_to_convergence,
    moving_success_rate,
    summarize,
)

C = ConvergenceCriterion(window=10, threshold=0.9, hold=0.8)


def test_moving_rate():
    sr = moving_success_rate([1, 0, 1, 1], 2)
    assert np.isnan(sr[0]) and list(sr[1:]) == [0.5, 0.5, 1.0]


def test_converges_at_first_confirmed_episode():
    s = [0] * 20 + [1] * 40
    r = episodes_to_convergence(s, C)
    # SR_10 first reaches 0.9 after 9 of the last 10 succeed: episode 29
    assert r.episodes == 29 and not r.censored and r.budget == 60


def test_dip_below_hold_restarts_the_search():
    s = [0] * 10 + [1] * 10 + [0] * 3 + [1] * 40
    r = episodes_to_convergence(s, C)
    # reached at 20 (SR=1.0) but drops to 0.7 at 23 -> not confirmed; next reach at 32
    assert r.episodes == 32


def test_never_converged_is_censored():
    s = [1, 0] * 100
    r = episodes_to_convergence(s, C)
    assert r.censored and r.value() == 200


def test_hold_window_must_fit_in_the_budget():
    s = [0] * 10 + [1] * 15  # reaches at 19 but only 6 episodes follow
    assert episodes_to_convergence(s, C).censored


def test_summary_marks_censoring():
    rs = [episodes_to_convergence([0] * 20 + [1] * 40, C),
          episodes_to_convergence([1, 0] * 50, C),
          episodes_to_convergence([1, 0] * 60, C)]
    s = summarize(rs)
    assert s["median"] == 100 and s["min"] == 29 and s["max"] == 120
    assert s["censored"] == 2 and s["median_censored"]


def test_bad_criterion():
    with pytest.raises(ValueError):
        ConvergenceCriterion(window=10, threshold=0.8, hold=0.9)
