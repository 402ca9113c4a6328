"""Confidence intervals across seeds: every seed is one independent experiment.

- A mean (a cell's measure, a point of a curve): Student's t interval,
  ``mean +- t(0.975, S - 1) * sd / sqrt(S)`` (``mean_ci``).
- A statistic of several means (a claim's ratio, its minimum or maximum over worlds): percentile
  bootstrap over seeds (``bootstrap_indices``, ``quantiles``), ``BOOTSTRAP_RESAMPLES`` resamples
  of the seed indices drawn from a generator seeded by the caller, so the intervals are as
  reproducible as the rest.

With a single seed there is no interval (``None``).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

CONFIDENCE = 0.95
BOOTSTRAP_RESAMPLES = 10_000
#: How ``results.json`` names the two methods (its ``"statistics"`` entry).
DESCRIPTION = {
    "confidence": CONFIDENCE,
    "means": "Student's t interval across seeds",
    "claims": f"percentile bootstrap over seeds, paired across cells, "
    f"{BOOTSTRAP_RESAMPLES} resamples, generator PCG64([seed, 0xB007])",
}


@functools.lru_cache(maxsize=256)
def t_critical(df: int, confidence: float = CONFIDENCE) -> float:
    """The two-sided Student's t critical value: ``P(|T| <= t) = confidence`` with ``df`` dof.

    Exact for integer ``df`` (Abramowitz & Stegun 26.7.3-4, a finite series), solved by bisection
    (200 steps of a series of ``df / 2`` terms, about 2 ms at ``df = 99``: kept per ``df``, as a
    run's every interval has the same).

    >>> round(t_critical(1), 3), round(t_critical(9), 3), round(t_critical(99), 3)
    (12.706, 2.262, 1.984)
    """
    if df < 1:
        raise ValueError(f"df={df} must be >= 1")
    if df > 2000:  # Cornish-Fisher expansion around the normal quantile, error < 1e-12 here
        z = 1.959963984540054 if confidence == CONFIDENCE else _normal_quantile(confidence)
        return (
            z
            + (z**3 + z) / (4 * df)
            + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)
            + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * df**3)
        )

    def central_probability(t: float) -> float:
        theta = math.atan(t / math.sqrt(df))
        cos2 = math.cos(theta) ** 2
        if df % 2 == 1:
            total, term = 0.0, math.cos(theta)
            for k in range(1, (df - 1) // 2 + 1):
                total += term
                term *= cos2 * (2 * k) / (2 * k + 1)
            return 2 / math.pi * (theta + math.sin(theta) * total)
        total, term = 0.0, 1.0
        for k in range(1, df // 2 + 1):
            total += term
            term *= cos2 * (2 * k - 1) / (2 * k)
        return math.sin(theta) * total

    low, high = 0.0, 1e6
    for _ in range(200):
        middle = (low + high) / 2
        if central_probability(middle) < confidence:
            low = middle
        else:
            high = middle
    return (low + high) / 2


def _normal_quantile(confidence: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(0.5 + confidence / 2)


def mean_ci(samples: Any) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Mean over axis 0 and its Student-t 95% interval (``None`` with fewer than 2 samples)."""
    samples = np.asarray(samples, dtype=np.float64)
    mean = samples.mean(axis=0)
    count = samples.shape[0]
    if count < 2:
        return mean, None, None
    half = t_critical(count - 1) * samples.std(axis=0, ddof=1) / math.sqrt(count)
    return mean, mean - half, mean + half


def scalar_ci(samples: Any) -> tuple[float, float | None, float | None]:
    """``mean_ci`` of per-seed scalars, as plain floats (for JSON)."""
    mean, low, high = mean_ci(samples)
    return float(mean), None if low is None else float(low), None if high is None else float(high)


def interval(low: Any, high: Any) -> list[float | None] | None:
    """``[low, high]`` for JSON (non-finite bounds as ``None``), or ``None`` without an interval."""
    return None if low is None else [finite_or_none(low), finite_or_none(high)]


def bootstrap_indices(seed: int, count: int) -> np.ndarray:
    """``[BOOTSTRAP_RESAMPLES, count]`` resampled seed indices, reproducible from ``seed``."""
    generator = np.random.Generator(np.random.PCG64([seed, 0xB007]))
    return generator.integers(0, count, size=(BOOTSTRAP_RESAMPLES, count))


def quantiles(values: np.ndarray) -> list[float | None]:
    """The 2.5% and 97.5% order statistics of the bootstrap values (inf kept, NaN -> None)."""
    tail = (1 - CONFIDENCE) / 2
    bounds = np.quantile(values, [tail, 1 - tail], method="inverted_cdf")
    return [finite_or_none(bound) for bound in bounds]


def finite_or_none(value: Any) -> float | None:
    """``value`` as a float, ``None`` where it is not finite (JSON has no inf or NaN)."""
    value = float(value)
    return value if math.isfinite(value) else None


def format_number(value: float | None) -> str:
    """A number for people: 3 significant digits, thousands unseparated, ``inf``/``n/a``."""
    if value is None:
        return "n/a"
    value = float(value)
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if math.isnan(value):
        return "n/a"
    if value == 0:
        return "0"
    magnitude = math.floor(math.log10(abs(value)))
    if magnitude >= 3:
        return f"{value:.0f}"
    return f"{value:.{max(2 - magnitude, 0)}f}"
