"""The paper's experiment (SPEC section 4): ``factorq paper``, a command of the runner's frame.

One *experiment* is one world x one algorithm: ``runs`` runs of ``episodes`` episodes. We run
``seeds`` independent experiments per cell of the paper's table and summarise them across seeds:

    config -> units (an algorithm x a shard of ``shard_seeds`` seeds, every selected world in one
           batch) -> per-seed totals and per-episode curves (each unit's, kept in OUT/units/)
           -> means and intervals across seeds -> claims C1-C5 -> results.json

Keys make experiment ``(seed index i, world w, algorithm a)`` draw the same numbers whatever else is
selected: its world key is number ``3 i + w`` of the world stream (shared by both algorithms:
common random numbers) and its policy key number ``2 (3 i + w) + a`` of the policy stream
(``paper_drivers.experiment_keys``). So a unit run alone, in any process, gives each of its
experiments the numbers it has in a run of all seeds at once, and ``results.json`` repeats to the
last digit (but for its ``timing``) whatever ``shard_seeds``, the backend, the threads, the
processes or the interruptions.

The intervals are ``factorq_trainers.analysis.stats``' (Student's t for means, a paired bootstrap
over seeds for the claims, seeded with ``config.seed``), the claims
``factorq_trainers.analysis.claims``', the files ``factorq_trainers.commands.paper.report``'s.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import asdict, is_dataclass, replace
from typing import Any

import numpy as np

from factorq_envs.regimes import REGIME_PERIODS
from factorq_trainers.analysis import stats
from factorq_trainers.analysis.claims import compute_claims
from factorq_trainers.analysis.stats import interval, mean_ci
from factorq_trainers.commands.paper import drivers
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.commands.paper.drivers import resolve_backend
from factorq_trainers.commands.paper.schema import CURVE_NAMES
from factorq_trainers.compiled import fast
from factorq_trainers.runner import frame, resources
from factorq_trainers.runner.kept import COUNT, NUMBER, TEXT

NAME = "paper"
HELP = "run the paper's experiment (3 worlds x 2 algorithms, many seeds) and report it"
DESCRIPTION = (
    "Run the paper's experiment (SPEC section 4) over many seeds and write results.json, "
    "figure3.png and report.md to --out."
)
FILES = {"json": "results.json", "report": "report.md", "figure": "figure3.png"}
HINT = "use fewer --seeds, --shard-seeds, --runs or --episodes, or a smaller --size"
WORK_UNIT = "episode"
#: The figure is drawn by a helper process started before torch loads (``cli``).
FIGURE_PROCESS = True
#: Memory of the summary besides the curves: the claims' bootstrap resamples, the results file's
#: text (measured: the default run peaks 90 MiB above the interpreter with torch, 1,000 seeds
#: 292 MiB; the estimate is within 5% of both).
SUMMARY_BYTES = 24 * 2**20
#: A unit's per-seed totals (summed over its runs) and the metric each sums.
RUN_SUMS = {
    "total_steps": "steps",
    "collisions": "collisions",
    "greedy_collisions": "greedy_collisions",
}
#: Per-seed totals of a run, averaged over the runs (``per_run``).
TOTALS = ("total_steps", "collisions", "greedy_collisions", "task_return")

CONFIG = PaperConfig

#: A unit's result: per world, each seed's totals and per-episode counts summed over its runs
#: (whole numbers), and its task return per run.
UNIT_RESULT = {
    "algorithm": TEXT,
    "backend": TEXT,
    "env_steps": COUNT,
    "worlds": [
        {
            "world": TEXT,
            "run_sums": {name: [COUNT] for name in RUN_SUMS},
            "task_return": [NUMBER],
            "curve_sums": {name: [[COUNT]] for name in CURVE_NAMES},
        }
    ],
}


# --------------------------------------------------------------------------------------------
# The units


def units(config: PaperConfig) -> list[dict[str, Any]]:
    """One unit per algorithm and shard of ``shard_seeds`` seeds (every selected world in its
    batch: the modular path steps a batch at about the cost of one experiment)."""
    stop = config.first_seed + config.seeds
    return [
        {
            "id": f"{algorithm}/{first}-{min(first + config.shard_seeds, stop)}",
            "algorithm": algorithm,
            "first_seed": first,
            "seeds": min(config.shard_seeds, stop - first),
        }
        for algorithm in config.methods
        for first in range(config.first_seed, stop, config.shard_seeds)
    ]


def work(config: PaperConfig, unit: dict[str, Any]) -> int:
    """A unit's episodes (what ``run_unit`` reports to ``progress``)."""
    return unit["seeds"] * len(config.regimes) * config.runs * config.episodes


def estimate(config: PaperConfig) -> resources.Estimate:
    """Peak memory of ``factorq paper`` with ``config``: one unit's batch (the larger
    algorithm's tables, the kernel's or the env's state, the metrics and their reduction) and
    every unit's result gathered for the summary (per-seed, per-episode counts and curves)."""
    world = config.world
    count = len(config.regimes) * min(config.shard_seeds, config.seeds)  # experiments of a unit
    positions, actions = world.num_cells * world.num_headings, world.num_actuators
    tables = 0
    for algorithm in config.methods:
        states = positions << world.num_sensors if algorithm == "q-learning" else positions
        # Q [E, states, A] float32, and Factor-Q's rho and kappa [E, A, 2**parents] (12 bytes)
        local = 0 if algorithm == "q-learning" else actions * (2 << world.num_sensors) * 12
        tables = max(tables, count * (states * actions * 4 + local))
    # The kernel's padded grid, obstacle positions and counters; the modular env holds the
    # obstacles [E, N] bool and a few observation TensorDicts besides.
    state = count * ((config.size + 2) ** 2 + 4 * config.obstacles + resources.EXPERIMENT_BYTES)
    if config.backend == "modular":
        state += 4 * count * world.num_cells
    unit_metrics = count * config.runs * config.episodes * resources.METRIC_BYTES
    # every seed's per-episode counts, kept and gathered: their JSON text and Python objects,
    # about 64 bytes a number (measured: 0.22 MiB more peak memory per seed of the default run)
    gathered = len(config.cells) * config.seeds * config.episodes * len(CURVE_NAMES) * 64
    parts = {
        "tables": tables,
        "run state": state,
        "metrics": unit_metrics * 2,  # the kernel's and their copy
        "curves": gathered + len(config.cells) * config.episodes * resources.CURVE_POINT_BYTES,
        "summary": SUMMARY_BYTES,
    }
    episodes = len(config.cells) * config.seeds * config.runs * config.episodes
    return resources.Estimate(parts, episodes * 2 * (config.size - 1), exact_steps=False)


def prepare(config: PaperConfig) -> None:
    """Choose the backend: a ValueError where the one asked for cannot run."""
    resolve_backend(config)


def describe(config: PaperConfig) -> str:
    """What runs (printed once the run is accepted), after why not on the fast path where
    ``auto`` fell back."""
    backend = resolve_backend(config)
    workers = drivers.threads_for(config, len(config.methods))
    notice = drivers.fallback_notice(config, backend, workers)
    told = (
        f"{len(config.cells) * config.seeds} experiments ({config.seeds} seeds x "
        f"{len(config.regimes)} worlds x {len(config.methods)} algorithms), "
        f"{config.runs} runs x {config.episodes} episodes each, {backend} backend"
    )
    return told if notice is None else f"{notice}\n{told}"


def processes(config: PaperConfig, units_: list[dict[str, Any]]) -> tuple[int, str]:
    """Processes for the units: on the modular path one per unit up to ``threads`` (default the
    cores torch sees; a batch of tiny tensors runs on one core), on the fast path one (the kernel
    uses every thread itself); ``units_``: ``units(config)``."""
    if resolve_backend(config) == "fast":
        return 1, "the compiled path uses every thread itself"
    return drivers.threads_for(config, len(units_)), "the modular path steps one batch per core"


def run_unit(
    config: PaperConfig,
    unit: dict[str, Any],
    progress: Callable[[int], None] | None = None,
    world: Any = None,
) -> dict[str, Any]:
    """One algorithm's experiments of one seed shard, every selected regime (``reduced``).

    Args:
        progress: called with the episodes done since its last call.
        world: another world than the grid (``run``'s), on the modular path.
    """
    algorithm = unit["algorithm"]
    shard = replace(
        config, first_seed=unit["first_seed"], seeds=unit["seeds"], methods=(algorithm,)
    )
    backend = "modular" if world is not None else resolve_backend(shard)
    keys = drivers.experiment_keys(shard, algorithm)
    report = progress or (lambda episodes: None)
    if backend == "fast":
        batch = drivers.run_fast(shard, algorithm, keys, report)
    else:
        batch = drivers.run_modular(shard, algorithm, keys, report, world)
    return reduced(config, unit, backend, {name: v.cpu().numpy() for name, v in batch.items()})


def reduced(
    config: PaperConfig, unit: dict[str, Any], backend: str, metrics: dict[str, np.ndarray]
) -> dict[str, Any]:
    """``unit``'s result from its raw metrics ``[W * seeds, runs, episodes]`` (regime-major):
    per regime, each seed's counts as whole sums over the runs (exact in float64, short in JSON;
    ``summarise`` divides them by ``runs``, which is what numpy's mean over the runs does), its
    task return per run averaged over the runs, and its per-episode counts summed over the runs;
    ``backend``: the path that ran it."""
    seeds = unit["seeds"]
    worlds = []
    for position, name in enumerate(config.regimes):
        cell = {
            key: values[position * seeds : (position + 1) * seeds]
            for key, values in metrics.items()
        }
        returns = cell["task_return"].astype(np.float64).sum(axis=2).mean(axis=1)  # [seeds]
        run_sums = {total: cell[key].sum(axis=(1, 2)).tolist() for total, key in RUN_SUMS.items()}
        curve_sums = {key: cell[key].sum(axis=1).tolist() for key in CURVE_NAMES}
        worlds.append(
            {
                "world": name,
                "run_sums": run_sums,
                "task_return": returns.tolist(),
                "curve_sums": curve_sums,
            }
        )
    return {
        "algorithm": unit["algorithm"],
        "backend": backend,
        "env_steps": int(metrics["steps"].sum()),
        "worlds": worlds,
    }


def check_unit(config: PaperConfig, unit: dict[str, Any], result: dict[str, Any]) -> str | None:
    """Why a kept ``result`` (``UNIT_RESULT``'s shape) cannot be ``unit``'s, or None: its worlds
    are the config's, each seed's numbers are there, each curve has ``episodes`` points."""
    worlds = [entry["world"] for entry in result["worlds"]]
    if worlds != list(config.regimes):
        return f"it holds the worlds {worlds}, not {list(config.regimes)}"
    for entry in result["worlds"]:
        lengths = [len(values) for values in entry["run_sums"].values()]
        lengths += [len(entry["task_return"])]
        lengths += [len(rows) for rows in entry["curve_sums"].values()]
        if set(lengths) != {unit["seeds"]}:
            return f"{entry['world']} holds {sorted(set(lengths))} seeds, not {unit['seeds']}"
        if None in entry["task_return"]:  # a run's return is always a finite number
            return f"{entry['world']}'s task_return holds null, not a finite number"
        points = {len(row) for rows in entry["curve_sums"].values() for row in rows}
        if points != {config.episodes}:
            return (
                f"{entry['world']}'s curves hold {sorted(points)} episodes, not {config.episodes}"
            )
    return None


# --------------------------------------------------------------------------------------------
# Summaries


def summarise(config: PaperConfig, outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    """``results.json``'s entries from the units (in ``units`` order): per cell, the seeds'
    means with 95% intervals and the per-episode curves, then the claims."""
    totals: dict[tuple[str, str], dict[str, list]] = {}
    episodes: dict[tuple[str, str], dict[str, list]] = {}
    for outcome in outcomes:  # in seed order within each algorithm
        for entry in outcome["worlds"]:
            key = (entry["world"], outcome["algorithm"])
            sums = totals.setdefault(key, {})
            for name, values in entry["run_sums"].items():
                sums.setdefault(name, []).extend(values)
            sums.setdefault("task_return", []).extend(entry["task_return"])
            for name, rows in entry["curve_sums"].items():
                episodes.setdefault(key, {}).setdefault(name, []).extend(rows)
    cells, runs = {}, config.runs
    for world, algorithm in config.cells:  # canonical order, whatever order they ran in
        # sums over the runs / runs: numpy's mean over the runs, to the last bit
        cell = {
            name: np.asarray(values, dtype=np.float64) / (1 if name == "task_return" else runs)
            for name, values in totals[world, algorithm].items()
        }
        curve_rows = {
            name: np.asarray(rows, dtype=np.float64) / runs
            for name, rows in episodes[world, algorithm].items()
        }
        totals_ci = {name: mean_ci(cell[name]) for name in TOTALS}  # (mean, low, high) each
        summary = {k: {"mean": float(v[0]), "ci95": interval(*v[1:])} for k, v in totals_ci.items()}
        ci = {name: mean_ci(curve_rows[name]) for name in CURVE_NAMES}  # (mean, low, high) each
        cells[f"{world}/{algorithm}"] = {
            "world": world,
            "algorithm": algorithm,
            "obstacle_period": REGIME_PERIODS[world],
            "per_seed": {name: cell[name].tolist() for name in TOTALS},
            "summary": summary,
            "curves": {name: mean.tolist() for name, (mean, _, _) in ci.items()},
            "curves_ci_low": {k: None if v[1] is None else v[1].tolist() for k, v in ci.items()},
            "curves_ci_high": {k: None if v[2] is None else v[2].tolist() for k, v in ci.items()},
        }
    backends = sorted({outcome["backend"] for outcome in outcomes})
    backend = backends[0] if len(backends) == 1 else "+".join(backends)
    timing: dict[str, Any] = {
        "backend": backend,
        "threads": drivers.threads_used(config, backends[0]) if backends else 1,
        "env_steps": sum(outcome["env_steps"] for outcome in outcomes),
    }
    if "modular" in backends and config.backend == "auto":
        # Why the compiled path did not run (a missing compiler, an unsupported body).
        reason = fast.unsupported_reason(config.world) or fast.unavailable_reason()
        if reason is not None:
            timing["fast_unavailable"] = reason
    return {
        "cells": cells,
        "claims": compute_claims(cells, config.seed),
        "statistics": dict(stats.DESCRIPTION),
        "timing": timing,
    }


def run(
    config: PaperConfig, progress: Callable[[int], None] | None = None, *, world: Any = None
) -> dict[str, Any]:
    """Every unit here, one after another; the results (what ``results.json`` holds).

    ``world``: another world than the config's grid, an ``factorq_envs.protocol.World`` (e.g.
    ``factorq_envs.corridor.Corridor``): the experiments of regime ``w`` run in it with ``w``'s
    obstacle period, on the modular path (``auto`` falls back to it with a one-line notice,
    ``backend="fast"`` is refused); the config's grid options are unused and ``results["world"]``
    names the world. ``progress``: called with the episodes done since its last call."""
    module = sys.modules[__name__]
    if world is not None:
        _check_foreign_world(world, config)
    # why not on the fast path, once (the units run here one after another)
    notice = drivers.fallback_notice(config, resolve_backend(config, world), 1, world)
    if notice is not None:
        print(notice, file=sys.stderr)
    if world is None:
        return frame.run_in_process(module, config, progress)
    results = frame.run_in_process(
        module, config, progress, lambda unit, report: run_unit(config, unit, report, world)
    )
    results["world"] = world_description(world)
    return results


def _check_foreign_world(world: Any, config: PaperConfig) -> None:
    """Refuse a ``world`` that ``run`` cannot take: one error naming it."""
    from factorq_envs.grid_world import FactoredGrid
    from factorq_envs.protocol import check_world

    check_world(world)
    if isinstance(world, FactoredGrid):
        raise ValueError(
            "world=FactoredGrid(...): the paper's grid is the config's own world; set its options "
            "in the PaperConfig (size, obstacles, body, sensors, ...) instead"
        )
    if config.backend == "fast":
        raise ValueError(
            f"backend='fast' cannot run world={type(world).__name__}(...): the compiled path "
            f"runs the grid only (use backend='auto' or 'modular')"
        )


def world_description(world: Any) -> dict[str, Any]:
    """``{"name", "config"}`` of a world other than the config's grid (``results["world"]``):
    its config's fields that are JSON scalars."""
    config = world.config
    fields_ = asdict(config) if is_dataclass(config) and not isinstance(config, type) else {}
    scalars = {key: value for key, value in fields_.items()
               if value is None or isinstance(value, bool | int | float | str)}  # fmt: skip
    return {"name": type(world).__name__, "config": scalars}
