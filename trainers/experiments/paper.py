"""The paper's experiment (SPEC section 4): config -> results.

One *experiment* is one world x one algorithm: ``runs`` runs of ``episodes`` episodes. We run
``seeds`` independent experiments per cell of the paper's table and summarise them across seeds:

    config -> keys per experiment -> one batch per algorithm (all worlds, all seeds) -> metrics
           -> per-seed means and per-episode curves -> claims C1-C5 -> results (a JSON-ready dict)

Keys make experiment ``(seed index i, world w, algorithm a)`` draw the same numbers whatever else is
selected: its world key is number ``3 i + w`` of the world stream (shared by both algorithms:
common random numbers) and its policy key number ``2 (3 i + w) + a`` of the policy stream
(``factorq_trainers.experiments.experiment.experiment_keys``).

The intervals are ``factorq_trainers.analysis.stats``' (Student's t for means, a paired bootstrap
over seeds for the claims, seeded with ``config.seed``), the claims
``factorq_trainers.analysis.claims``', and the files
``factorq_trainers.reports.report.write_results``'.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, is_dataclass
from typing import Any, NamedTuple

import numpy as np

from factorq_envs.regimes import REGIME_PERIODS, REGIMES  # noqa: F401 - paper.REGIMES
from factorq_torch.base.config import ALGORITHMS  # noqa: F401 - paper.ALGORITHMS
from factorq_trainers.analysis import stats
from factorq_trainers.analysis.claims import compute_claims
from factorq_trainers.analysis.stats import interval, mean_ci
from factorq_trainers.experiments.paper_config import (  # noqa: F401 - its public names
    BACKENDS,
    PaperConfig,
    config_dict,
    config_from_dict,
)
from factorq_trainers.experiments.paper_drivers import (  # noqa: F401
    MODULAR_PARALLEL_SECONDS_PER_EPISODE,
    MODULAR_SECONDS_PER_EPISODE,
    PROCESS_BYTES,
    BatchKeys,
    Job,
    _modular_in_process,
    _processes_fit,
    _run_fast,
    _run_modular,
    _run_side_by_side,
    backend_driver,
    experiment_keys,
    fallback_notice,
    modular_processes,
    modular_threads,
    resolve_backend,
    threads_used,
)
from factorq_trainers.runner import checkpoint, resources
from factorq_trainers.runner.results import SCHEMA_VERSION, software_versions
from factorq_trainers.runner.resume_checks import check_checkpoint
from factorq_trainers.runner.schema import CURVE_NAMES

NAME = "paper"
HELP = "run the paper's experiment (3 worlds x 2 algorithms, many seeds) and report it"
DESCRIPTION = (
    "Run the paper's experiment (SPEC section 4) over many seeds and write results.json, "
    "figure3.png and report.md to --out."
)
#: paper keeps its finer frame (mid-run checkpoints, the figure process, shards on Dask).
FRAME = "factorq_trainers.experiments.paper_frame"
FILES = {"json": "results.json", "report": "report.md", "figure": "figure3.png"}
REPORT = "factorq_trainers.reports.report"
CURVES = CURVE_NAMES  # per-episode curves; task return is reported per run
#: Seconds between two calls of ``run``'s ``progress``, at most (a bar needs no more).
PROGRESS_SECONDS = 0.1


CONFIG = PaperConfig


class Progress(NamedTuple):
    """What ``run`` reports to its ``progress`` callback after every chunk of work."""

    episodes_completed: int
    episodes_total: int
    experiments_finished: int
    experiments_total: int


ProgressCallback = Callable[[Progress], None]


def run(
    config: PaperConfig,
    progress: ProgressCallback | None = None,
    *,
    checkpoint_every: checkpoint.Every | str | int | None = None,
    resume: checkpoint.Checkpoint | None = None,
    world: Any = None,
    curves_ready: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Run the paper's experiment and return its results (the schema of ``results.json``).

    ``progress`` is called with a ``Progress`` after every chunk of work. Everything but the
    ``"timing"`` section is a function of ``config`` alone (same config, same numbers), however
    often the run was interrupted and resumed.

    ``checkpoint_every`` (episodes summed over all experiments, or seconds: ``"30s"``) saves the
    whole state to ``<config.out>/checkpoint/`` that often (see
    ``factorq_trainers.runner.checkpoint``);
    the caller removes it with ``checkpoint.remove(config.out)`` once the results are written.
    ``resume`` (``checkpoint.load(out)``, with ``config`` from ``resume_config``) continues from
    a checkpoint, saving at its interval unless ``checkpoint_every`` is given. A new run refuses
    an ``out`` that holds an unfinished run's checkpoint.

    ``world``: another world than the config's grid, an ``factorq_envs.protocol.World`` (e.g.
    ``factorq_envs.corridor.Corridor``): the experiments of world name ``w`` run in it with ``w``'s
    obstacle period, on the modular path (``auto`` falls back to it with a one-line notice;
    ``backend="fast"`` is refused), without checkpoints; the config's grid options are unused and
    ``results["world"]`` names the world.

    ``curves_ready`` is called with the results so far (``config``, ``cells`` and, for another
    world, ``world``: what Figure 3 reads) as soon as the curves are summarised, before the claims
    are computed: ``factorq paper`` has the figure drawn meanwhile.

    On the modular path the algorithms run side by side, each in a process of its own
    (``modular_processes``: with two or more CPU threads allowed, without checkpoints and another
    ``world``; a checkpoint holds one running algorithm's state, so a checkpointed run keeps
    them one after the other in this process): the same numbers, ``results["timing"]`` records
    ``processes``. An error in a process is raised here; a process that dies is a
    ``processes.WorkerError`` naming its algorithm; Ctrl-C ends them.
    """
    started = time.perf_counter()
    if world is not None:
        _check_foreign_world(world, checkpoint_every, resume)
    checkpointing = checkpoint_every is not None or resume is not None
    estimate = resources.paper_estimate(
        config, checkpointing=checkpoint_every is not None, world=world
    )
    resources.check(estimate, "run", resources.PAPER_HINT)  # before anything is allocated
    backend = resolve_backend(config, world)
    driver = backend_driver(backend)
    count = 1
    if backend == "modular":
        count = modular_processes(config, world, checkpointing)
        if count > 1 and not _processes_fit(config, count):
            count = 1  # the batches side by side do not fit: one after the other, as they do
    notice = fallback_notice(config, backend, world, count)
    if notice is not None:
        print(notice, file=sys.stderr)
    if resume is not None:
        saved = {"first_seed": 0, **resume.config}  # from before shards: no first_seed
        checkpoint.check_same_config(
            saved, config_dict(config), f"resume='{resume.path.parents[1]}'"
        )
        check_checkpoint(resume, config)
    if checkpoint_every is None and resume is not None:
        checkpoint_every = resume.every  # a resumed run goes on saving as it did
    checkpoints = checkpoint.Checkpointer(
        config.out, config_dict(config), backend, every=checkpoint_every, resume=resume
    )
    experiments_total = len(config.cells) * config.seeds
    episodes_total = experiments_total * config.runs * config.episodes

    def report_progress() -> None:
        if progress is not None:
            progress(
                Progress(
                    checkpoints.episodes_completed,
                    episodes_total,
                    checkpoints.experiments_finished,
                    experiments_total,
                )
            )

    reported = [time.monotonic()]

    def advance_progress(episodes: int, experiments: int) -> None:
        # (the modular path reports after almost every step: the callback is passed on at most
        # every PROGRESS_SECONDS, and once more when the experiments are done)
        checkpoints.advance(episodes, experiments)
        now = time.monotonic()
        if now - reported[0] >= PROGRESS_SECONDS:
            reported[0] = now
            report_progress()

    report_progress()
    if count > 1:  # the algorithms side by side (nothing finished: no resume)
        _run_side_by_side(config, count, checkpoints, advance_progress)
    metrics: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for algorithm in config.algorithms:
        batch = checkpoints.finished.get(algorithm)
        if batch is None:
            keys = experiment_keys(config, algorithm)
            batch = driver(Job(config, algorithm, keys, advance_progress, checkpoints, world))
            checkpoints.finish(algorithm, batch)
        for position, name in enumerate(config.worlds):
            rows = slice(position * config.seeds, (position + 1) * config.seeds)
            metrics[name, algorithm] = {
                name: values[rows].cpu().numpy() for name, values in batch.items()
            }
    report_progress()  # where the experiments ended
    summarised = None
    if curves_ready is not None:

        def summarised(partial: dict[str, Any]) -> None:
            if world is not None:
                partial = {**partial, "world": world_description(world)}
            curves_ready(partial)

    results = summarise(config, metrics, curves_ready=summarised)
    wall = checkpoints.elapsed_s
    env_steps = int(sum(cell["steps"].sum() for cell in metrics.values()))
    results["timing"] = {
        "wall_s": round(wall, 3),
        "backend": backend,
        "threads": threads_used(config, backend, count),
        "env_steps": env_steps,
        "env_steps_per_s": round(env_steps / max(wall, 1e-9)),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if backend == "modular":
        results["timing"]["processes"] = count
    if backend == "modular" and config.backend == "auto":
        from factorq_trainers.compiled import fast

        # Why the compiled path did not run (a missing compiler, an unsupported body).
        reason = (
            fast.unsupported_reason(config.world if world is None else world)
            or fast.unavailable_reason()
        )
        if reason is not None:
            results["timing"]["fast_unavailable"] = reason
    if world is not None:
        results["world"] = world_description(world)
    if checkpoint_every is not None or resume is not None:
        results["timing"]["checkpoints"] = {
            "every": None if checkpoints.every is None else str(checkpoints.every),
            "saved": checkpoints.saves,
            "save_s": round(checkpoints.save_seconds, 3),
            "resumed_at_episode": None if resume is None else resume.episodes_completed,
            "this_process_s": round(time.perf_counter() - started, 3),
        }
    return results


def _check_foreign_world(world: Any, checkpoint_every: Any, resume: Any) -> None:
    """Refuse a ``world`` that ``run`` cannot take: one error naming it."""
    from factorq_envs.grid_world import FactoredGrid
    from factorq_envs.protocol import check_world

    check_world(world)
    if isinstance(world, FactoredGrid):
        raise ValueError(
            "world=FactoredGrid(...): the paper's grid is the config's own world; set its options "
            "in the PaperConfig (size, obstacles, body, sensors, ...) instead"
        )
    if checkpoint_every is not None or resume is not None:
        raise ValueError(
            f"world={type(world).__name__}(...): checkpoints hold the paper grid's state only; "
            f"run another world without checkpoint_every and resume"
        )


def world_description(world: Any) -> dict[str, Any]:
    """``{"name", "config"}`` of a world other than the config's grid (``results["world"]``)."""
    config = world.config
    fields_ = asdict(config) if is_dataclass(config) and not isinstance(config, type) else {}
    return {
        "name": type(world).__name__,
        "config": {key: value for key, value in fields_.items() if _json_scalar(value)},
    }


def _json_scalar(value: Any) -> bool:
    return value is None or isinstance(value, bool | int | float | str)


def resume_config(
    saved: dict[str, Any], given: dict[str, Any], directory: str | os.PathLike
) -> PaperConfig:
    """The config to resume the run of ``directory`` with (``checkpoint.resumed_config``); a
    checkpoint from before shards had no ``first_seed`` (it reads as 0)."""
    saved = {"first_seed": 0, **saved}
    return checkpoint.resumed_config(saved, given, directory, config_from_dict, config_dict)


# --------------------------------------------------------------------------------------------
# Summaries


def summarise(
    config: PaperConfig,
    metrics: dict[tuple[str, str], dict[str, np.ndarray]],
    *,
    curves_ready: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Results from raw metrics ``{(world, algorithm): {name: [S, runs, episodes]}}``;
    ``curves_ready`` is called with the results so far (``schema_version``, ``config``, ``cells``)
    before the claims are computed (``run``)."""
    cells = {}
    for world, algorithm in config.cells:  # canonical order, whatever order they ran in
        cell = metrics[world, algorithm]
        per_run = {  # [S]: totals over the episodes of a run, averaged over the runs
            "total_steps": cell["steps"].sum(axis=2).mean(axis=1),
            "collisions": cell["collisions"].sum(axis=2).mean(axis=1),
            "greedy_collisions": cell["greedy_collisions"].sum(axis=2).mean(axis=1),
            "task_return": cell["task_return"].astype(np.float64).sum(axis=2).mean(axis=1),
        }
        summary = {}
        for name, values in per_run.items():
            mean, low, high = mean_ci(values)
            summary[name] = {"mean": float(mean), "ci95": interval(low, high)}
        curves, lows, highs = {}, {}, {}
        for name in CURVES:
            per_episode = cell[name].mean(axis=1)  # [S, E], mean over runs
            mean, low, high = mean_ci(per_episode)
            curves[name] = mean.tolist()
            lows[name] = None if low is None else low.tolist()
            highs[name] = None if high is None else high.tolist()
        cells[f"{world}/{algorithm}"] = {
            "world": world,
            "algorithm": algorithm,
            "obstacle_period": REGIME_PERIODS[world],
            "per_seed": {name: values.tolist() for name, values in per_run.items()},
            "summary": summary,
            "curves": curves,
            "curves_ci_low": lows,
            "curves_ci_high": highs,
        }
    results = {"schema_version": SCHEMA_VERSION, "config": config_dict(config), "cells": cells}
    if curves_ready is not None:
        curves_ready(results)
    results["claims"] = compute_claims(cells, config.seed)
    results["statistics"] = dict(stats.DESCRIPTION)
    results["software"] = software_versions()
    return results
