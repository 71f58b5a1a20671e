import numpy as np
import pytest

from geonav.errors import ConfigError
from geonav.experiments.stats import format_summary, seed_summary

pytest.importorskip("rliable", reason="seed statistics need the stats extra: "
                    "pip install 'geonav[stats]'")
sps = pytest.importorskip("scipy.stats", reason="scipy comes with the stats extra")


def test_iqm_median_and_intervals():
    values = [310, 120, 900, 400, 100, 320, 500, 300, 700, 600]
    s = seed_summary(values, [False] * 10, reps=1000, seed=1)
    assert s["n"] == 10 and s["n_censored"] == 0
    assert s["median"] == 360.0 and (s["min"], s["max"]) == (100.0, 900.0)
    # IQM of 10 runs: drop 2 from each end, mean of the middle 6
    assert s["iqm"] == pytest.approx(np.mean(sorted(values)[2:8]))
    assert s["iqm"] == pytest.approx(sps.trim_mean(values, 0.25))
    lo, hi = s["iqm_ci"]
    assert min(values) <= lo < s["iqm"] < hi <= max(values)
    lo, hi = s["median_ci"]
    assert lo < s["median"] < hi
    assert not any(s[k] for k in ("median_censored", "iqm_censored", "max_censored"))
    again = seed_summary(values, [False] * 10, reps=1000, seed=1)
    assert again["iqm_ci"] == s["iqm_ci"]  # seeded bootstrap


def test_censored_runs_make_lower_bounds_only_where_they_count():
    # two runs censored at the 1000-episode budget: the largest ranks, cut from the IQM
    values = [100, 120, 300, 310, 320, 400, 500, 600, 1000, 1000]
    s = seed_summary(values, [False] * 8 + [True] * 2, reps=500)
    assert s["n_censored"] == 2 and s["max_censored"] and not s["iqm_censored"]
    assert not s["median_censored"] and not s["min_censored"]
    # three of four censored: the median and the IQM are lower bounds
    s = seed_summary([200, 1000, 1000, 1000], [False, True, True, True], reps=500)
    assert s["median_censored"] and s["iqm_censored"] and not s["min_censored"]
    assert format_summary(s).startswith("1000+ [200-1000+], IQM 1000+")
    # a censored run below observed ones (a shorter budget) still bounds the median
    s = seed_summary([50, 300, 400], [True, False, False], reps=500)
    assert s["median_censored"] and s["min_censored"]


def test_stratified_by_task_and_edge_cases():
    rng = np.random.default_rng(0)
    x = np.stack([rng.normal(100, 5, 6), rng.normal(400, 5, 6)], axis=1)  # (runs, tasks)
    s = seed_summary(x, np.zeros_like(x, bool), reps=500)
    assert s["n"] == 12
    # runs resampled within each task keep both tasks in every resample: the CI stays
    # around the two-task IQM instead of spanning 100..400
    lo, hi = s["iqm_ci"]
    assert 150 < lo < s["iqm"] < hi < 350
    one = seed_summary([42.0], [False])
    assert one["iqm"] == one["median"] == 42.0 and one["iqm_ci"] == [42.0, 42.0]
    empty = seed_summary([], [])
    assert empty["n"] == 0 and empty["iqm"] is None and format_summary(empty) == "n/a"
    with pytest.raises(ConfigError, match="same shape"):
        seed_summary([1, 2, 3], [False, True])
    with pytest.raises(ConfigError, match="finite"):
        seed_summary([1, float("nan")], [False, False])
