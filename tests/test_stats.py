"""Confidence intervals: Student's t against the tables, the interval's arithmetic."""

from __future__ import annotations

import math

import numpy as np
import pytest

from factorq_trainers.analysis.stats import mean_ci, t_critical


def test_t_critical_matches_tables():
    # Student's t table, two-sided 95%: df 1 -> 12.706, 2 -> 4.303, 10 -> 2.228, 30 -> 2.042
    for df, expected in [(1, 12.706), (2, 4.303), (10, 2.228), (30, 2.042), (5000, 1.9604)]:
        assert t_critical(df) == pytest.approx(expected, abs=1e-3)


def test_mean_ci_is_mean_plus_minus_t_times_standard_error():
    samples = np.array([1.0, 2.0, 3.0])  # mean 2, sd 1, se 1/sqrt(3), t(2) = 4.303
    mean, low, high = mean_ci(samples)
    assert mean == 2.0 and high - mean == pytest.approx(4.303 / math.sqrt(3), abs=1e-3)
    assert mean_ci(samples[:1])[1] is None
