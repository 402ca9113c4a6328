"""Running a sweep (``factorq sweep``): every configuration run whole (``frame.run_in_process``)
as one task on an executor, its results dict kept in ``OUT/configs/<digest>.json`` (sealed and
tied by ``kept``) as it finishes, then ``sweep.json``'s dict gathered from those files, each
configuration's cells taken by its command's ``sweep_cells``.

A configuration whose kept file passes its checks is not run again, so a killed sweep continues
where it stopped, and a sweep that adds axis values runs only the new configurations. A
configuration's numbers depend on it alone: a sweep's are the same in-process, on any number of
workers and after any number of interruptions.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from factorq_trainers.distributed.sweep_spec import (
    CONFIGS_DIRECTORY,
    SweepSpec,
    _reports_of,
    config_digest,
)
from factorq_trainers.runner import cluster, frame, kept, registry
from factorq_trainers.runner import results as result_files


def config_result_path(directory: str | os.PathLike, config: Any) -> Path:
    """``directory/<digest>.json``: where a configuration's results are kept."""
    return Path(directory) / f"{config_digest(config)}.json"


#: What ``kept`` calls a kept configuration result in its messages.
CONFIG_FILE = "configuration file"


def _read_config_result(path: Path, command: str, config: Any) -> dict[str, Any]:
    """The results of ``command`` for ``config`` kept at ``path``: sealed, kept for this command
    and configuration, values checked (a ValueError naming it otherwise)."""
    check = getattr(_reports_of(command), "results_problem", None)  # the command's own check
    return kept.read_sealed(
        path, CONFIG_FILE, kept_for=kept.tie(command, config_digest(config)), check=check
    )


def _pending_configs(
    directory: Path, configs: Sequence[Any], force: bool, command: str
) -> list[Any]:
    """The configurations of ``configs`` to run: those without a kept result, and (``force``)
    those whose kept result fails its checks; without ``force`` such a file is refused."""
    return [
        config
        for config in configs
        if not kept.reusable(
            config_result_path(directory, config),
            functools.partial(_read_config_result, command=command, config=config),
            force,
        )
    ]


def _gathered(
    spec: SweepSpec,
    pending: list,
    started: float,
    executor: cluster.InProcess | cluster.DaskExecutor,
) -> dict[str, Any]:
    """``sweep.json``'s dict: one row per configuration read back from ``OUT/configs/``;
    ``pending``: the configurations run now."""
    computed = time.perf_counter() - started
    command, reports = spec.command, _reports_of(spec.command)
    directory = Path(spec.out) / CONFIGS_DIRECTORY
    configs = spec.configurations()
    rows = []
    for config, point in zip(configs, spec.points(), strict=True):
        path = config_result_path(directory, config)
        results = _read_config_result(path, command, config)  # digest, tie, values checked
        try:  # a kept file is the user's: it may have been edited or cut short
            cells_of = reports.sweep_cells(results)
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as error:
            raise ValueError(
                f"configuration file {path} is not a factorq {command} result ({error!r}): "
                f"{kept.REMEDY}"
            ) from None
        rows.append(
            {
                "values": point,
                "digest": config_digest(config),
                "config": frame.plain(config),
                "results_file": f"{CONFIGS_DIRECTORY}/{path.name}",
                "cells": cells_of,
                "claims": {  # the paper's claims, where the command has them
                    name: {key: claim[key] for key in ("value", "ci95", "pass")}
                    for name, claim in results.get("claims", {}).items()
                },
            }
        )
    return {
        "command": command,
        "measures": list(reports.SWEEP_MEASURES),
        "axes": spec.axes,
        "base": frame.plain(dict(spec.base)),
        "seeds": spec.seeds,
        "configurations": frame.plain(rows),
        "timing": {
            "wall_s": round(time.perf_counter() - started, 3),
            "compute_s": round(computed, 3),
            "where": executor.description,
            "configurations_total": len(configs),
            "configurations_run_now": len(pending),
        },
        "software": result_files.software_versions(),
    }


def _units_task(command: str, config: Any) -> dict[str, Any]:
    return frame.run_in_process(registry.load(command), config)


def run_sweep(
    spec: SweepSpec,
    executor: cluster.InProcess | cluster.DaskExecutor,
    progress: Callable[[int, int], None] | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Run and keep every configuration of ``spec`` not already kept, then gather ``sweep.json``'s
    dict. ``progress(done, total)`` counts configurations (those found on disk are done from the
    start). A kept file that fails its checks is refused before any work, or with ``force``
    recomputed."""
    started = time.perf_counter()
    directory = Path(spec.out) / CONFIGS_DIRECTORY
    configs = spec.configurations()
    pending = _pending_configs(directory, configs, force, spec.command)
    done = len(configs) - len(pending)
    progress = progress or (lambda done, total: None)
    progress(done, len(configs))
    names = [f"{spec.command}-{config_digest(config)}" for config in pending]
    task = functools.partial(_units_task, spec.command)
    for index, results in executor.map(task, pending, names):
        directory.mkdir(parents=True, exist_ok=True)
        kept_for = kept.tie(spec.command, config_digest(pending[index]))
        kept.write_sealed(config_result_path(directory, pending[index]), results, kept_for)
        done += 1
        progress(done, len(configs))
    return _gathered(spec, pending, started, executor)
