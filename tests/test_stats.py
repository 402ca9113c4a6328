"""Confidence intervals: Student's t against the tables, Wilson's against scipy's binomial test,
the bootstrap inside the possible range, and the issue-28 example that a t interval got wrong."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import binomtest

from factorq_trainers.analysis.stats import (
    bootstrap_mean_ci,
    mean_ci,
    scalar_ci,
    t_critical,
    wilson_ci,
)


def test_t_critical_matches_tables():
    # Student's t table, two-sided 95%: df 1 -> 12.706, 2 -> 4.303, 10 -> 2.228, 30 -> 2.042
    for df, expected in [(1, 12.706), (2, 4.303), (10, 2.228), (30, 2.042), (5000, 1.9604)]:
        assert t_critical(df) == pytest.approx(expected, abs=1e-3)
    assert t_critical(4, 0.90) == pytest.approx(2.132, abs=1e-3)  # the table's 90% column


def test_mean_ci_is_mean_plus_minus_t_times_standard_error():
    samples = np.array([1.0, 2.0, 3.0])  # mean 2, sd 1, se 1/sqrt(3), t(2) = 4.303
    mean, low, high = mean_ci(samples)
    assert mean == 2.0 and high - mean == pytest.approx(4.303 / math.sqrt(3), abs=1e-3)
    assert mean_ci(samples[:1])[1] is None


@pytest.mark.parametrize("successes, trials", [(0, 3), (1, 3), (3, 4), (10, 10), (37, 100)])
def test_wilson_is_the_binomial_wilson_interval(successes, trials):
    outcomes = np.array([1.0] * successes + [0.0] * (trials - successes))
    mean, low, high = wilson_ci(outcomes)
    expected = binomtest(successes, trials).proportion_ci(method="wilson")
    assert mean == successes / trials
    assert (low, high) == pytest.approx((expected.low, expected.high), abs=1e-12)


def test_wilson_by_hand():
    # one success in one trial, z = 1.96: centre (1 + z^2/2) / (1 + z^2), half z sqrt(z^2/4) / (1
    # + z^2); low = (1 + z^2/2 - z^2/2) / (1 + z^2) = 1 / (1 + z^2) = 0.2066, high = 1
    mean, low, high = wilson_ci([1.0])
    z = 1.959963984540054
    assert (low, high) == pytest.approx((1 / (1 + z * z), 1.0), abs=1e-12)


def test_wilson_takes_proportions_only():
    with pytest.raises(ValueError, match=r"must be in \[0, 1\]"):
        wilson_ci([0.5, 1.5])


def test_bootstrap_stays_between_the_seeds_and_is_reproducible():
    rng = np.random.default_rng(3)
    for count in (2, 3, 5, 20):
        samples = rng.exponential(10.0, size=(count, 7))  # skewed, >= 0
        mean, low, high = bootstrap_mean_ci(samples, seed=11)
        assert (low >= samples.min(axis=0)).all() and (high <= samples.max(axis=0)).all()
        assert (low <= mean).all() and (mean <= high).all()
        again = bootstrap_mean_ci(samples, seed=11)
        assert (again[1] == low).all() and (again[2] == high).all()
    # a wide sample: the interval narrows with more seeds (it is an interval, not [min, max])
    wide = rng.exponential(10.0, size=400)
    _, low, high = bootstrap_mean_ci(wide, seed=0)
    assert high - low < 0.5 * (wide.max() - wide.min())
    assert low < 10.0 < high


def test_bootstrap_of_constant_seeds_is_the_value_and_one_seed_has_none():
    mean, low, high = bootstrap_mean_ci(np.array([[2.0, 1.0], [2.0, 3.0], [2.0, 5.0]]), seed=0)
    assert low[0] == high[0] == 2.0 and low[1] < 3.0 < high[1]
    assert bootstrap_mean_ci([4.0], seed=0)[1] is None


# Issue 28: `factorq minigrid --sizes 5 --seeds 3` printed a success rate of 0.79 [0.15, 1.43]
# and steps to the goal 35.8 [-18.8, 90.4]. That run's per-seed values were not kept; these print
# exactly what it printed (success: the share of a seed's final episodes, 1/2, 6/7 and 1; steps:
# a seed's mean over its successful final episodes). The same command rerun in this session
# (Q-learning's cell; Factor-Q, learned: steps) gave the same failure with other numbers.
ISSUE = {"success": [1 / 2, 6 / 7, 1.0], "steps": [10.4, 48.2, 48.8]}
RERUN = {"success": [0.5, 1.0, 0.4], "steps": [43.6, 49 / 6, 12.0]}


def _rounded(interval, digits):
    return tuple(round(value, digits) for value in interval)


def test_the_issue_example_t_leaves_the_range():
    assert _rounded(scalar_ci(ISSUE["success"]), 2) == (0.79, 0.15, 1.43)
    assert _rounded(scalar_ci(ISSUE["steps"]), 1) == (35.8, -18.8, 90.4)
    assert _rounded(scalar_ci(RERUN["success"]), 2) == (0.63, -0.17, 1.43)
    assert _rounded(scalar_ci(RERUN["steps"]), 1) == (21.3, -27.0, 69.6)


@pytest.mark.parametrize("run", [ISSUE, RERUN])
def test_the_issue_example_new_intervals_stay_in_range(run):
    mean, low, high = scalar_ci(run["success"], wilson_ci)
    assert 0 < low < mean < high < 1
    # Wilson with the seed as the trial is no narrower than Wilson for 3 Bernoulli trials could be
    # at this mean, yet shorter than the t interval, which spent most of its width outside [0, 1]
    t_low, t_high = scalar_ci(run["success"])[1:]
    assert high - low < t_high - t_low
    steps = scalar_ci(run["steps"], lambda values: bootstrap_mean_ci(values, seed=0))
    assert min(run["steps"]) <= steps[1] < steps[0] < steps[2] <= max(run["steps"])


def test_the_issue_example_by_hand():
    # Wilson, p = 11/14 = 0.785714, n = 3, z^2 = 3.841459: centre (p + z^2/6) / (1 + z^2/3)
    # = 1.425957 / 2.280486 = 0.625286; half-width z / (1 + z^2/3) sqrt(p (1 - p) / 3 + z^2 / 36)
    # = 0.859448 * sqrt(0.056122 + 0.106707) = 0.859448 * 0.403521 = 0.346805
    _, low, high = wilson_ci(ISSUE["success"])
    assert (low, high) == pytest.approx((0.625286 - 0.346805, 0.625286 + 0.346805), abs=1e-5)
