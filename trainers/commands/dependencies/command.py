"""``factorq dependencies``: Factor-Q that learns its own sensor-actuator pairing.

Per *setting* (a body, a sensor layout, noise, a change), ``seeds`` experiments of ``runs`` x
``episodes`` episodes (task tables reset per run, local knowledge kept, SPEC section 4) per method,
on the same worlds (common random numbers), each run by ``methods.py`` beside it:
``factor-q-learned`` (``StructureLearner``, told nothing of the body: ``run_learned``, compiled or
modular, the same numbers bit for bit), the oracle ``factor-q`` (the paper's ``LocalRewardTable``
with the true dependency), ``factor-q-joint`` (one local table per actuator over the pattern of
*all* sensors, the paper's footnote 2) and ``q-learning`` (``run_compiled``, where their tables
fit: ``skipped_reason``), and opt-in ``dqn`` (on the oracle's step budget: ``run_dqn``) and
``factor-q-gated`` (``GatedLocalRewardNetwork``: ``run_gated``). Every experiment receives its
sensors in its own random order (``factorq_envs.permutation.PermuteSensors``), redrawn at run
``change_run`` in the ``change`` setting; the joint table, Q-learning and the gated network see
them in the learner's orders, changed at the same moment, while the oracle is told the true
pairing at every moment (the same as running it in the world's own order).

Structure metrics (``factor-q-learned`` only), per experiment: the local samples (firings) per
actuator until it holds the right parents and keeps them to the end (the experiment's value: the
largest over its actuators; in the ``change`` setting counted from the change), wrong commitments
(commitments to a parent set other than the truth of that moment), the structural Hamming distance
at the end (parents missing or extra, an open actuator counting as "no parents").

Writes ``dependencies.json``, ``dependencies.png`` and ``dependencies.md`` to ``out``.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from factorq_torch.base.validation import MAX_PARENTS
from factorq_trainers.analysis.stats import bootstrap_indices, interval, quantiles, wilson_ci
from factorq_trainers.analysis.vocabulary import label
from factorq_trainers.commands.dependencies import methods
from factorq_trainers.commands.dependencies.config import (
    METHODS,
    SAMPLES_TARGET,
    SAMPLES_TARGET_CHANGE,
    DependenciesConfig,
)
from factorq_trainers.runner import frame, resources
from factorq_trainers.runner.kept import COUNT, FRACTION, NON_NEGATIVE, TEXT

NAME = "dependencies"
HELP = "learn which sensors each actuator depends on, against the oracle pairing"
DESCRIPTION = (
    "Run the structure learner against the oracle pairing, the full joint table and "
    "Q-learning on the settings; write dependencies.json, dependencies.png and dependencies.md "
    "to --out."
)
HINT = "use fewer --seeds, --runs or --episodes, or fewer --settings"

CONFIG = DependenciesConfig

_RATIO = {"ratio": NON_NEGATIVE, "ci": (None, [NON_NEGATIVE])}
_AGAINST_ORACLE = {
    "collisions": _RATIO,
    "greedy_collisions": _RATIO,
    "learning_speed": _RATIO,
    # the task measures of both sides beside the ratios (issue 39)
    "absolute?": {"steps_per_episode": {"*": NON_NEGATIVE}, "fraction_truncated": {"*": FRACTION}},
}
#: A unit's result (``run_unit``), what a kept one must hold (``runner.kept``'s schema).
UNIT_RESULT = {
    "summary": {
        "methods": {
            "*": {
                "collisions_per_experiment": NON_NEGATIVE,
                "greedy_collisions_per_experiment": NON_NEGATIVE,
                "steps_per_run": NON_NEGATIVE,
                "steps_per_episode?": NON_NEGATIVE,
                "fraction_truncated?": FRACTION,
                "step_budget?": COUNT,
                "episodes_per_experiment?": NON_NEGATIVE,
                "collisions_per_episode": [NON_NEGATIVE],
            }
        },
        "gated_structure?": {
            "fraction_right_at_end": FRACTION,
            "hamming_at_end_mean": NON_NEGATIVE,
        },
        "gated_against_oracle?": _AGAINST_ORACLE,
        "structure?": {
            "samples_until_right_median": NON_NEGATIVE,
            "samples_until_right_p90": NON_NEGATIVE,
            "samples_target": COUNT,
            "fraction_right_within_target": FRACTION,
            "fraction_right_within_target_ci95": (None, [FRACTION]),
            "fraction_right_at_end": FRACTION,
            "wrong_commitments_per_1000": NON_NEGATIVE,
            "hamming_at_end_mean": NON_NEGATIVE,
            "reopened_per_experiment": NON_NEGATIVE,
            "curve": {"env_steps": [COUNT], "fraction_right": [FRACTION]},
        },
        "against_oracle?": _AGAINST_ORACLE,
    },
    "skipped": {"*": TEXT},
}


# --------------------------------------------------------------------------------------------
# Statistics


def _ratio(numerator: np.ndarray, denominator: np.ndarray, seed: int) -> dict[str, Any]:
    """Ratio of means with a paired bootstrap 95% interval over the seeds."""
    value = float(numerator.mean() / denominator.mean()) if denominator.mean() else math.inf
    if numerator.size < 2:
        return {"ratio": value, "ci": None}
    index = bootstrap_indices(seed, numerator.size)
    top, bottom = numerator[index].mean(axis=1), denominator[index].mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = np.where(bottom > 0, top / np.where(bottom > 0, bottom, 1), np.inf)
    return {"ratio": value, "ci": quantiles(ratios)}


def _percentile(values: np.ndarray, q: float) -> float | None:
    value = float(np.quantile(values, q, method="inverted_cdf"))
    return value if math.isfinite(value) else None


def summarise_setting(
    config: DependenciesConfig, setting: str, runs: dict[str, dict[str, Any]]
) -> dict[str, Any]:
    """Per method its totals; for ``factor-q-learned`` the structure metrics and the ratios to the
    oracle."""
    summary: dict[str, Any] = {"methods": {}}
    totals = {}
    for method, result in runs.items():
        if method == "dqn":  # a step budget, no runs: its totals only
            collisions, greedy = result["totals"]["collisions"], result["totals"]["greedy"]
            summary["methods"][method] = {
                "collisions_per_experiment": float(collisions.mean()),
                "greedy_collisions_per_experiment": float(greedy.mean()),
                "steps_per_run": None,
                "step_budget": result["budget"],
                "episodes_per_experiment": float(np.mean(result["episodes"])),
                "collisions_per_episode": result["collisions_per_episode"],
            }
            continue
        metrics = result["metrics"]
        steps = metrics["steps"].to(torch.float64)  # [S, runs, episodes]
        collisions = metrics["collisions"].sum(dim=(1, 2)).double().numpy()
        greedy = metrics["greedy_collisions"].sum(dim=(1, 2)).double().numpy()
        per_run = steps.sum(dim=2).mean(dim=1).numpy()
        totals[method] = {"collisions": collisions, "greedy": greedy, "steps": per_run}
        # truncated: not at the goal after max_steps (a goal step's task return is -steps + 1)
        truncated = (metrics["task_return"].to(torch.float64) == -steps).double()
        per_episode = metrics["collisions"].double().flatten(1).mean(dim=0).tolist()
        summary["methods"][method] = {
            "collisions_per_experiment": float(collisions.mean()),
            "greedy_collisions_per_experiment": float(greedy.mean()),
            "steps_per_run": float(per_run.mean()),
            "steps_per_episode": float(steps.mean()),
            "fraction_truncated": float(truncated.mean()),
            "collisions_per_episode": per_episode,
        }
    gated = runs.get("factor-q-gated")
    if gated is not None:
        summary["gated_structure"] = {
            "fraction_right_at_end": float(np.mean(gated["right_at_end"])),
            "hamming_at_end_mean": float(np.mean(gated["hamming_at_end"])),
        }
        if "factor-q" in totals:
            summary["gated_against_oracle"] = _against_oracle(
                summary["methods"], totals, "factor-q-gated", config.seed
            )
    learned = runs.get("factor-q-learned")
    if learned is None:
        return summary
    until = np.asarray(learned["samples_until_right"], dtype=np.float64)
    target = SAMPLES_TARGET_CHANGE if setting == "change" else SAMPLES_TARGET
    summary["structure"] = {
        "samples_until_right_median": _percentile(until, 0.5),
        "samples_until_right_p90": _percentile(until, 0.9),
        "samples_target": target,
        "fraction_right_within_target": float((until <= target).mean()),
        "fraction_right_within_target_ci95": interval(*wilson_ci(until <= target)[1:]),
        "fraction_right_at_end": float(np.isfinite(until).mean()),
        "wrong_commitments_per_1000": 1000 * float(np.mean(learned["wrong_commitments"])),
        "hamming_at_end_mean": float(np.mean(learned["hamming_at_end"])),
        "reopened_per_experiment": float(np.mean(learned["reopened"])),
        "curve": learned["curve"],
    }
    if "factor-q" in totals:
        summary["against_oracle"] = _against_oracle(
            summary["methods"], totals, "factor-q-learned", config.seed
        )
    return summary


def _against_oracle(
    summaries: dict[str, Any], totals: dict[str, Any], method: str, seed: int
) -> dict[str, Any]:
    """``method`` against the oracle: ratios, and both sides' task measures (issue 39)."""
    mine, oracle = totals[method], totals["factor-q"]
    return {
        "collisions": _ratio(mine["collisions"], oracle["collisions"], seed),
        "greedy_collisions": _ratio(mine["greedy"], oracle["greedy"], seed),
        # learning speed = 1 / steps per run: its speed / the oracle's
        "learning_speed": _ratio(oracle["steps"], mine["steps"], seed),
        "absolute": {  # steps per episode and episodes truncated: a failure both share shows
            name: {side: summaries[side][name] for side in (method, "factor-q")}
            for name in ("steps_per_episode", "fraction_truncated")
        },
    }


# --------------------------------------------------------------------------------------------
# The experiment


def units(config: DependenciesConfig) -> list[dict[str, Any]]:
    """One unit per setting x regime (its methods share worlds, and DQN's budget is the
    oracle's); its id, the key of its ``dependencies.json`` entry: the setting's name when one
    regime runs, ``setting/regime`` when several do."""
    several = len(config.regimes) > 1
    return [
        {"id": f"{setting}/{regime}" if several else setting, "setting": setting, "regime": regime}
        for setting in config.settings
        for regime in config.regimes
    ]


def run_unit(
    config: DependenciesConfig,
    unit: dict[str, Any],
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Every method of ``config`` in the unit's setting and regime: its summary and the methods
    skipped."""
    setting = unit["setting"]
    config = dataclasses.replace(config, regimes=(unit["regime"],))
    runs: dict[str, dict[str, Any]] = {}
    skipped = {}
    for method in (method for method in METHODS if method in config.methods):
        reason = methods.skipped_reason(config, setting, method)
        if reason is not None:
            skipped[method] = reason
            continue
        if method == "factor-q-learned":
            runs[method] = methods.run_learned(config, setting)
        elif method == "dqn":
            runs[method] = methods.run_dqn(config, setting, methods._budget(config, setting, runs))
        elif method == "factor-q-gated":
            runs[method] = methods.run_gated(config, setting)
        else:
            runs[method] = methods.run_compiled(config, setting, method)
    return {"summary": summarise_setting(config, setting, runs), "skipped": skipped}


def summarise(config: DependenciesConfig, outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    """``dependencies.json``'s entries from the units (in ``units`` order), keyed by their
    ids."""
    results: dict[str, Any] = {
        "settings": {},
        "skipped": {},
        "methods": {method: label(method) for method in METHODS},
    }
    for unit, outcome in zip(units(config), outcomes, strict=True):
        if outcome["skipped"]:
            results["skipped"][unit["id"]] = outcome["skipped"]
        results["settings"][unit["id"]] = outcome["summary"]
    return results


def estimate(config: DependenciesConfig) -> resources.Estimate:
    """Peak memory of ``factorq dependencies`` with ``config``: the largest unit's (they run one
    after another) learner (8 float64 arrays ``[S, A, C, 2**max_parents]``, ``C`` the candidate
    parent sets, and their copy), task and local tables (the joint table's ``2**K`` entries where
    they fit) and metrics. Measured: 3.0 GiB estimated for 3,000 seeds, peak RSS 3.2 GiB."""
    largest, steps = 0, 0
    episodes = config.seeds * config.runs * config.episodes
    for setting in config.settings:
        world = config.world_of(setting)
        sensors, actions = world.num_sensors, world.num_actuators
        candidates = sum(math.comb(sensors, p) for p in range(min(config.max_parents, sensors) + 1))
        # the kernel's counts and the copy ``learner_state()`` hands the summary
        counts = 2 * 8 * 8 * actions * candidates * (1 << min(config.max_parents, sensors))
        tables = world.num_cells * world.num_headings * actions * 4
        joint = actions * (1 << sensors) * 12 if sensors <= MAX_PARENTS else 0
        per_experiment = counts + 2 * tables + joint + resources.EXPERIMENT_BYTES
        largest = max(
            largest, config.seeds * per_experiment + 3 * episodes * resources.METRIC_BYTES
        )
        steps += episodes * len(config.methods) * len(config.regimes) * 2 * (config.size - 1)
    return resources.Estimate({"learners, tables and metrics": largest}, steps, exact_steps=False)


def run(config: DependenciesConfig) -> dict[str, Any]:
    """Every setting x method, here; the results (what ``dependencies.json`` holds)."""
    return frame.run_in_process(sys.modules[__name__], config)
