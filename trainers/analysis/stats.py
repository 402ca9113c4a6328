"""Confidence intervals across seeds, every seed one independent experiment; which interval a
measure gets follows from the values it can take (docs/decisions.md, "Which interval each report
uses"): Student's t for unbounded means (``mean_ci``), Wilson's score interval with the seed as the
trial for proportions (``wilson_ci``), the BCa bootstrap for other bounded means
(``bootstrap_mean_ci``), and for a statistic of several means (a claim's ratio, minimum or
maximum) a percentile bootstrap over seeds, paired across cells (``bootstrap_indices``,
``quantiles``). Resamples come from ``PCG64([seed, 0xB007])``, the caller's seed. With one seed
there is no interval (``None``), except Wilson's.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from statistics import NormalDist
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
    """The two-sided Student's t critical value (``scipy.stats.t.ppf``):
    ``P(|T| <= t) = confidence`` with ``df >= 1`` degrees of freedom (the seeds less one).

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
    """Mean over axis 0 of ``[seeds, ...]`` and its Student-t 95% interval (``None`` with fewer
    than 2 seeds)."""
    samples = np.asarray(samples, dtype=np.float64)
    mean = samples.mean(axis=0)
    count = samples.shape[0]
    if count < 2:
        return mean, None, None
    half = t_critical(count - 1) * samples.std(axis=0, ddof=1) / math.sqrt(count)
    return mean, mean - half, mean + half


def wilson_ci(samples: Any) -> Interval:
    """Mean over axis 0 of per-seed proportions ``[seeds, ...]`` in [0, 1] and Wilson's 95% score
    interval with ``n`` seeds (``z`` the normal quantile): centre ``(p + z^2/2n) / (1 + z^2/n)``,
    half-width ``z / (1 + z^2 / n) * sqrt(p (1 - p) / n + z^2 / 4n^2)``; inside [0, 1].

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
    z = NormalDist().inv_cdf(0.5 + CONFIDENCE / 2)
    scale = 1 + z * z / count
    centre = (mean + z * z / (2 * count)) / scale
    half = z / scale * np.sqrt(mean * (1 - mean) / count + z * z / (4 * count * count))
    return mean, np.clip(centre - half, 0, 1), np.clip(centre + half, 0, 1)  # clip: rounding only


def bootstrap_mean_ci(samples: Any, seed: int) -> Interval:
    """Mean over axis 0 of ``[seeds, ...]`` and its BCa bootstrap 95% interval over the seeds
    (``scipy.stats.bootstrap``; resamples from the run's master ``seed``). The bounds stay in
    ``[min, max]`` of the seeds; where every seed has the same value the interval is that value
    (BCa is undefined there). ``None`` with fewer than 2 seeds.

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
    with warnings.catch_warnings():  # BCa warns on (and returns NaN for) constant columns
        warnings.simplefilter("ignore")
        result = bootstrap(
            (samples,),
            np.mean,
            axis=0,
            n_resamples=BOOTSTRAP_RESAMPLES,
            confidence_level=CONFIDENCE,
            method="BCa",
            rng=_generator(seed),
        )
    low = np.where(constant, mean, result.confidence_interval.low)
    high = np.where(constant, mean, result.confidence_interval.high)
    # floating-point sums of a resample may differ from the seeds' extremes in the last bit
    smallest, largest = samples.min(axis=0), samples.max(axis=0)
    return mean, np.clip(low, smallest, largest), np.clip(high, smallest, largest)


def seed_bands(
    rows: Sequence[Sequence[float | None]] | np.ndarray, seed: int, every_seed: bool = False
) -> dict[str, list[float | None]]:
    """A curve's mean over seeds at each point and its 95% BCa bootstrap band (``rows``: one
    curve per seed, ``None`` or NaN where a seed has no value, none past a shorter row's end), as
    JSON lists (``None``: no value; no band from a single seed). One bootstrap per set of seeds
    present, over those seeds (the return of ``factorq gym`` is missing before a seed's first
    episode), or with ``every_seed`` only where every seed has a value (``factorq compare``)."""
    points = max(len(row) for row in rows)
    values = np.full((len(rows), points), np.nan)
    for index, row in enumerate(rows):
        values[index, : len(row)] = [np.nan if value is None else value for value in row]
    mean, low, high = (np.full(points, np.nan) for _ in range(3))
    present = ~np.isnan(values)  # [seeds, points]
    for pattern in {tuple(column) for column in present.T.tolist()}:
        seeds = np.array(pattern, dtype=bool)
        if not seeds.any() or (every_seed and not seeds.all()):
            continue
        columns = (present.T == seeds).all(axis=1)
        mean[columns], band_low, band_high = bootstrap_mean_ci(values[seeds][:, columns], seed)
        if band_low is not None and band_high is not None:
            low[columns], high[columns] = band_low, band_high
    bands = (("mean", mean), ("low", low), ("high", high))
    return {name: [finite_or_none(value) for value in array] for name, array in bands}


def scalar_ci(samples: Any, method: Any = mean_ci) -> tuple[float, float | None, float | None]:
    """``method`` (``mean_ci``, ``wilson_ci`` or a ``functools.partial`` of
    ``bootstrap_mean_ci``) of one value per seed, as plain floats (for JSON)."""
    mean, low, high = method(samples)
    return float(mean), None if low is None else float(low), None if high is None else float(high)


def interval(low: Any, high: Any) -> list[float | None] | None:
    """``[low, high]`` for JSON (non-finite bounds as ``None``), or ``None`` without an interval
    (either bound missing)."""
    return None if low is None or high is None else [finite_or_none(low), finite_or_none(high)]


def _generator(seed: int) -> np.random.Generator:
    return np.random.Generator(np.random.PCG64([seed, 0xB007]))


def bootstrap_indices(seed: int, count: int) -> np.ndarray:
    """``[BOOTSTRAP_RESAMPLES, count]`` resampled seed indices, reproducible from ``seed``."""
    return _generator(seed).integers(0, count, size=(BOOTSTRAP_RESAMPLES, count))


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
    value = math.nan if value is None else float(value)
    if math.isnan(value):
        return "n/a"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return "0" if value == 0 else f"{value:.{max(2 - math.floor(math.log10(abs(value))), 0)}f}"


def with_ci(value: float | None, ci: Any) -> str:
    """``format_number(value)``, then its 95% interval ``[low, high]`` where it has one."""
    text = format_number(value)
    return f"{text} [{format_number(ci[0])}, {format_number(ci[1])}]" if ci else text


#: What a report says where a ratio of counts would say nothing (``count_ratio``).
TOO_LITTLE_DATA = "too little data"


def count_ratio(numerator: float | None, denominator: float | None) -> float | None:
    """``numerator / denominator`` of two counts (or means of counts), or ``None`` when either
    is 0 or missing: a ratio with a zero side is 0 or unbounded, which says nothing about how
    far apart they are (a report then says ``TOO_LITTLE_DATA`` and gives both counts).

    >>> count_ratio(150.0, 7.5), count_ratio(0.0, 3.0), count_ratio(0.0, 0.0)
    (20.0, None, None)
    """
    if numerator is None or denominator is None or numerator <= 0 or denominator <= 0:
        return None
    return float(numerator) / float(denominator)
