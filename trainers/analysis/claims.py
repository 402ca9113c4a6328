"""The paper's claims as checks (SPEC section 5): C1-C5 from the per-seed means of each cell
(the ``per_seed`` lists of ``results.json``), each claim's statistic with a percentile bootstrap
interval over seeds, paired across cells because the cells of one seed index share their world's
random numbers (``stats``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from factorq_envs.regimes import REGIMES
from factorq_torch.base.config import ALGORITHMS
from factorq_trainers.analysis import stats
from factorq_trainers.analysis.stats import finite_or_none, format_number
from factorq_trainers.analysis.vocabulary import among, label

#: The measures of a cell, per run (totals over the episodes of a run, mean over the runs).
MEASURES = ("total_steps", "collisions", "greedy_collisions")
MEASURE_LABELS = {measure: measure.replace("_", " ") for measure in MEASURES}
ALGORITHM_LABELS = {name: label(name) for name in among("q-learning", "factor-q")}

CLAIM_STATEMENTS = {
    "C1": "Factor-Q beats Q-learning on every measure, in every world",
    "C2": "in the static world learning speed is not significantly different",
    "C3": "static-world collision avoidance is dramatically better",
    "C4": "Factor-Q learns dynamic worlds nearly as fast as the static one; "
    "Q-learning falls to about 57% in the worst case",
    "C5": "greedy collisions improved by over two orders of magnitude",
}
CLAIM_THRESHOLDS = {
    "C1": "Factor-Q / Q-learning <= 1 for all 3 measures in all 3 worlds",
    "C2": "Q-learning / Factor-Q total steps in [0.8, 1.25]",
    "C3": "Q-learning / Factor-Q collisions > 10",
    "C4": "Factor-Q moving/static speed >= 0.85 in both moving worlds; "
    "Q-learning worst in [0.45, 0.70]",
    "C5": "Q-learning / Factor-Q greedy collisions > 100 in every world",
}
MOVING = ("semi-dynamic", "dynamic")


def _means_of(cells: dict[str, Any], indices: np.ndarray | None) -> Callable[..., Any]:
    """Means per (world, algorithm, measure): point estimates, or bootstrap resamples ``[B]``
    (``indices``), each computed once (the claims share them) and never modified by its users."""

    @functools.cache
    def means(world: str, algorithm: str, measure: str) -> Any:
        values = np.asarray(cells[f"{world}/{algorithm}"]["per_seed"][measure], np.float64)
        return values.mean() if indices is None else values[indices].mean(axis=1)  # [B]

    return means


def _ratio(numerator: Any, denominator: Any) -> Any:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.divide(numerator, denominator)


#: The claims that compare Q-learning / Factor-Q on one measure: their worlds and their bar.
_AGAINST_FACTOR_Q = {
    "C2": (("static",), "total_steps", lambda ratio: (ratio >= 0.8) & (ratio <= 1.25)),
    "C3": (("static",), "collisions", lambda ratio: ratio > 10),
    "C5": (REGIMES, "greedy_collisions", lambda ratio: ratio > 100),
}


def _measures(claim: str, means: Callable[..., Any]) -> dict[str, Any]:
    """The comparisons a claim is made of: ``{name: (ratio, pass or None)}``."""
    measures = {}
    if claim == "C1":
        for world in REGIMES:
            for measure in MEASURES:
                factor_q = means(world, "factor-q", measure)
                q_learning = means(world, "q-learning", measure)
                name = f"{world} {MEASURE_LABELS[measure]}, Factor-Q / Q-learning"
                measures[name] = (_ratio(factor_q, q_learning), factor_q <= q_learning)
    elif claim == "C4":
        for algorithm in ALGORITHMS:
            static = means("static", algorithm, "total_steps")
            for world in MOVING:
                # speed = 1 / mean total steps, so moving/static speed = static steps / moving steps
                ratio = _ratio(static, means(world, algorithm, "total_steps"))
                label = f"{ALGORITHM_LABELS[algorithm]} speed, {world} / static"
                measures[label] = (ratio, ratio >= 0.85 if algorithm == "factor-q" else None)
    else:
        worlds, measure, bar = _AGAINST_FACTOR_Q[claim]
        for world in worlds:
            ratio = _ratio(means(world, "q-learning", measure), means(world, "factor-q", measure))
            name = f"{world} {MEASURE_LABELS[measure]}, Q-learning / Factor-Q"
            measures[name] = (ratio, bar(ratio))
    return measures


def _worst(measures: dict[str, Any], pick: Callable, keys: list[str] | None = None) -> Any:
    values = [measures[key][0] for key in (keys or list(measures))]
    return pick(np.stack(np.broadcast_arrays(*values)), axis=0)


def _headline(claim: str, measures: dict[str, Any]) -> tuple[Any, Any]:
    """The claim's headline statistic (from its measures) and whether it passes: C4's worst
    speed ratio of each algorithm, else the largest ratio (C1) or the smallest, and all pass."""
    if claim == "C4":
        factor_q = _worst(measures, np.min, [key for key in measures if "Factor-Q" in key])
        q_learning = _worst(measures, np.min, [key for key in measures if "Q-learning" in key])
        passed = (factor_q >= 0.85) & (q_learning >= 0.45) & (q_learning <= 0.70)
        return {"factor-q": factor_q, "q-learning": q_learning}, passed
    passed = np.all(np.stack([measure[1] for measure in measures.values()]), 0)
    return _worst(measures, np.max if claim == "C1" else np.min), passed


_EVERY_CELL = [f"{world}/{algorithm}" for world in REGIMES for algorithm in ALGORITHMS]
_STATIC_CELLS = [f"static/{algorithm}" for algorithm in ALGORITHMS]
#: The cells each claim needs.
_CLAIM_CELLS = dict(
    C1=_EVERY_CELL, C2=_STATIC_CELLS, C3=_STATIC_CELLS, C4=_EVERY_CELL, C5=_EVERY_CELL
)


def compute_claims(cells: dict[str, Any], seed: int = 0) -> dict[str, Any]:
    """Claims C1-C5 of SPEC section 5 from ``cells`` (only their ``per_seed`` lists are read).

    Each claim: ``statement``, ``threshold``, ``value`` (its statistic; C4 has one per algorithm),
    ``ci95`` (bootstrap interval of ``value``, ``None`` with one seed), ``pass`` (``None`` when a
    cell it needs was not run), ``detail`` and ``measures`` (the comparisons it is made of).
    """
    seeds = {len(cell["per_seed"]["total_steps"]) for cell in cells.values()}
    if len(seeds) > 1:
        raise ValueError(f"cells have different numbers of seeds: {sorted(seeds)}")
    count = seeds.pop() if seeds else 0
    indices = stats.bootstrap_indices(seed, count) if count >= 2 else None
    point_means = _means_of(cells, None)
    boot_means = None if indices is None else _means_of(cells, indices)
    claims = {}
    for claim in CLAIM_STATEMENTS:
        entry: dict[str, Any] = {
            "statement": CLAIM_STATEMENTS[claim], "threshold": CLAIM_THRESHOLDS[claim],
            "value": None, "ci95": None, "pass": None, "detail": "", "measures": [],
        }  # fmt: skip
        claims[claim] = entry
        missing = [cell for cell in _CLAIM_CELLS[claim] if cell not in cells]
        if missing:
            entry["detail"] = f"not evaluated: needs {', '.join(missing)}, which were not run"
            continue
        point = _measures(claim, point_means)
        value, passed = _headline(claim, point)
        boot_value = boot = None
        if boot_means is not None:
            boot = _measures(claim, boot_means)
            boot_value, _ = _headline(claim, boot)
        for name, (measure_value, measure_pass) in point.items():
            entry["measures"].append(
                {
                    "name": name,
                    "value": finite_or_none(measure_value),
                    "ci95": None if boot is None else stats.quantiles(boot[name][0]),
                    "pass": None if measure_pass is None else bool(measure_pass),
                }
            )
        if isinstance(value, dict):
            entry["value"] = {key: finite_or_none(item) for key, item in value.items()}
            entry["ci95"] = boot_value and {k: stats.quantiles(v) for k, v in boot_value.items()}
        else:
            entry["value"] = finite_or_none(value)
            entry["ci95"] = None if boot_value is None else stats.quantiles(boot_value)
        entry["pass"] = bool(passed)
        entry["detail"] = _detail(claim, entry, value)
    return claims


def _detail(claim: str, entry: dict[str, Any], value: Any) -> str:
    """One sentence: what was compared, the outcome, and why."""
    measures = {measure["name"]: measure for measure in entry["measures"]}
    undefined = [name for name, measure in measures.items() if measure["value"] is None]
    note = f"; undefined (0 in a denominator, reported as null): {', '.join(undefined)}"
    note = note if undefined else ""
    if claim == "C1":
        failing = [name for name, measure in measures.items() if not measure["pass"]]
        if failing:
            return "Factor-Q > Q-learning on: " + "; ".join(failing) + note
        closest = max(measures, key=lambda name: _sortable(measures[name]["value"]))
        return (
            f"Factor-Q <= Q-learning in all {len(measures)} comparisons; closest: {closest} = "
            f"{format_number(value)}{note}"
        )
    if claim == "C2":
        inside = "inside" if entry["pass"] else "outside"
        return f"{next(iter(measures))} = {format_number(value)}, {inside} [0.8, 1.25]{note}"
    if claim == "C3":
        outcome = ">" if entry["pass"] else "not >"
        return f"{next(iter(measures))} = {format_number(value)} ({outcome} 10){note}"
    if claim == "C4":
        factor_q, q_learning = value["factor-q"], value["q-learning"]
        return (
            f"Factor-Q worst moving/static speed {format_number(factor_q)} "
            f"({'>=' if factor_q >= 0.85 else 'below'} 0.85); Q-learning worst "
            f"{format_number(q_learning)} ({'in' if 0.45 <= q_learning <= 0.70 else 'outside'} "
            f"[0.45, 0.70]){note}"
        )
    smallest = min(measures, key=lambda name: _sortable(measures[name]["value"]))
    failing = [name.split(" ")[0] for name, measure in measures.items() if not measure["pass"]]
    outcome = f"not > 100 in: {', '.join(failing)}" if failing else "> 100 in every world"
    return f"smallest ratio {format_number(value)} ({smallest.split(' ')[0]}); {outcome}{note}"


def _sortable(value: float | None) -> float:
    return math.inf if value is None else value
