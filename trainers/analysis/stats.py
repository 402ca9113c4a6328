"""Confidence intervals across seeds: every seed is one independent experiment.

Which interval a measure gets depends on what values it can take (docs/decisions.md, "Which
interval each report uses"):

- An unbounded mean, or one far from its bounds over many seeds (the paper's cells and curves):
  Student's t interval, ``mean +- t(0.975, S - 1) * sd / sqrt(S)`` (``mean_ci``; the quantile
  from ``scipy.stats.t``).
- A proportion (a success rate, a fraction of experiments; per-seed values in [0, 1]): Wilson's
  score interval with the seed as the trial (``wilson_ci``). It never leaves [0, 1]; for per-seed
  rates between 0 and 1 it is conservative, as ``p (1 - p)`` bounds the variance of any [0, 1]
  quantity with mean ``p``.
- Any other bounded mean over few seeds (steps to a goal, collisions, returns): the BCa bootstrap
  of the mean (``bootstrap_mean_ci``, ``scipy.stats.bootstrap``). Its bounds are means of
  resampled seeds, so they lie between the smallest and the largest seed: inside whatever range
  the quantity has.
- A statistic of several means (a claim's ratio, its minimum or maximum over worlds): percentile
  bootstrap over seeds, paired across cells (``bootstrap_indices``, ``quantiles``),
  ``BOOTSTRAP_RESAMPLES`` resamples of the seed indices drawn from a generator seeded by the
  caller, so the intervals are as reproducible as the rest.

With a single seed there is no interval (``None``), except Wilson's, which is defined for one trial.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

CONFIDENCE = 0.95
BOOTSTRAP_RESAMPLES = 10_000
#: How ``results.json`` names the methods (its ``"statistics"`` entry).
DESCRIPTION = {
    "confidence": CONFIDENCE,
    "means": "Student's t interval across seeds",
    "claims": f"percentile bootstrap over seeds, paired across cells, "
    f"{BOOTSTRAP_RESAMPLES} resamples, generator PCG64([seed, 0xB007])",
    "proportions": "Wilson score interval, the seed as the trial",
    "bounded means": f"BCa bootstrap of the mean over seeds (scipy.stats.bootstrap), "
    f"{BOOTSTRAP_RESAMPLES} resamples, generator PCG64([seed, 0xB007])",
}

Interval = tuple[np.ndarray, np.ndarray | None, np.ndarray | None]


@functools.lru_cache(maxsize=256)
def t_critical(df: int, confidence: float = CONFIDENCE) -> float:
    """The two-sided Student's t critical value: ``P(|T| <= t) = confidence`` with ``df`` dof.

    Args:
        df: degrees of freedom (the number of seeds less one), at least 1.
        confidence: the interval's coverage, in (0, 1).

    ``scipy.stats.t.ppf``: within 1e-16 of the exact quantile at ``df = 99`` (the hand-written
    series and bisection it replaced were within 3e-15, docs/decisions.md).

    >>> round(t_critical(1), 3), round(t_critical(9), 3), round(t_critical(99), 3)
    (12.706, 2.262, 1.984)
    """
    if df < 1:
        raise ValueError(f"df={df} must be >= 1")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence={confidence} must be in (0, 1)")
    from scipy.stats import t

    return float(t.ppf(0.5 + confidence / 2, df))


def mean_ci(samples: Any) -> Interval:
    """Mean over axis 0 and its Student-t 95% interval (``None`` with fewer than 2 samples).

    Args:
        samples: ``[seeds, ...]`` values, one row per seed.
    """
    samples = np.asarray(samples, dtype=np.float64)
    mean = samples.mean(axis=0)
    count = samples.shape[0]
    if count < 2:
        return mean, None, None
    half = t_critical(count - 1) * samples.std(axis=0, ddof=1) / math.sqrt(count)
    return mean, mean - half, mean + half


def wilson_ci(samples: Any) -> Interval:
    """Mean over axis 0 of per-seed proportions and Wilson's 95% score interval with ``n`` seeds.

    Args:
        samples: ``[seeds, ...]`` values in [0, 1] (a seed's success rate, or 0/1 per seed).

    Wilson's interval for ``p = mean`` with ``n`` trials, ``z`` the normal quantile: centre
    ``(p + z^2 / 2n) / (1 + z^2 / n)``, half-width
    ``z / (1 + z^2 / n) * sqrt(p (1 - p) / n + z^2 / 4n^2)``; inside [0, 1] for every ``p``.

    >>> mean, low, high = wilson_ci([1, 1, 1, 0])  # 3 of 4: scipy's binomtest gives the same
    >>> round(float(low), 4), round(float(high), 4)
    (0.3006, 0.9544)
    """
    samples = np.asarray(samples, dtype=np.float64)
    if samples.size and not ((samples >= 0) & (samples <= 1)).all():
        raise ValueError("wilson_ci takes proportions: every value must be in [0, 1]")
    mean = samples.mean(axis=0)
    count = samples.shape[0]
    if count < 1:
        return mean, None, None
    z = _normal_quantile(CONFIDENCE)
    scale = 1 + z * z / count
    centre = (mean + z * z / (2 * count)) / scale
    half = z / scale * np.sqrt(mean * (1 - mean) / count + z * z / (4 * count * count))
    return mean, np.clip(centre - half, 0, 1), np.clip(centre + half, 0, 1)  # clip: rounding only


def bootstrap_mean_ci(samples: Any, seed: int) -> Interval:
    """Mean over axis 0 and its BCa bootstrap 95% interval over the seeds (``scipy.stats``).

    Args:
        samples: ``[seeds, ...]`` values, one row per seed.
        seed: the run's master seed (the resamples are drawn from ``PCG64([seed, 0xB007])``).

    The bounds are means of resampled seeds, so they never leave ``[min, max]`` of the seeds:
    a bounded quantity keeps its bounds. Where every seed has the same value the interval is that
    value (BCa is undefined there). ``None`` with fewer than 2 seeds.

    >>> mean, low, high = bootstrap_mean_ci([30.0, 10.0, 2.0], seed=0)  # steps: never below 0
    >>> 2.0 <= float(low) < float(mean) < float(high) <= 30.0
    True
    """
    import warnings

    from scipy.stats import bootstrap

    samples = np.asarray(samples, dtype=np.float64)
    mean = samples.mean(axis=0)
    if samples.shape[0] < 2:
        return mean, None, None
    constant = (samples == samples[:1]).all(axis=0)
    generator = np.random.Generator(np.random.PCG64([seed, 0xB007]))
    with warnings.catch_warnings():  # BCa warns on (and returns NaN for) constant columns
        warnings.simplefilter("ignore")
        result = bootstrap(
            (samples,),
            np.mean,
            axis=0,
            n_resamples=BOOTSTRAP_RESAMPLES,
            confidence_level=CONFIDENCE,
            method="BCa",
            rng=generator,
        )
    low = np.where(constant, mean, result.confidence_interval.low)
    high = np.where(constant, mean, result.confidence_interval.high)
    # floating-point sums of a resample may differ from the seeds' extremes in the last bit
    low = np.clip(low, samples.min(axis=0), samples.max(axis=0))
    high = np.clip(high, samples.min(axis=0), samples.max(axis=0))
    return mean, low, high


def _normal_quantile(confidence: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(0.5 + confidence / 2)


def scalar_ci(samples: Any, method: Any = mean_ci) -> tuple[float, float | None, float | None]:
    """``method`` (``mean_ci`` unless given) of per-seed scalars, as plain floats (for JSON).

    Args:
        samples: one value per seed.
        method: ``mean_ci``, ``wilson_ci`` or ``bootstrap_mean_ci`` with its seed bound
            (``functools.partial``).
    """
    mean, low, high = method(samples)
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


#: What a report says where a ratio of counts would say nothing (``count_ratio``).
TOO_LITTLE_DATA = "too little data"


def count_ratio(numerator: float | None, denominator: float | None) -> float | None:
    """``numerator / denominator`` of two counts (or means of counts), or ``None`` when either
    is 0 or missing: a ratio with a zero side is 0 or unbounded, which says nothing about how
    far apart they are (a report then says ``TOO_LITTLE_DATA`` and gives both counts).

    Example:
        >>> count_ratio(150.0, 7.5), count_ratio(0.0, 3.0), count_ratio(0.0, 0.0)
        (20.0, None, None)
    """
    if numerator is None or denominator is None or numerator <= 0 or denominator <= 0:
        return None
    return float(numerator) / float(denominator)
