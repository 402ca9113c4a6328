"""Shards: a run of the paper's experiment cut into contiguous ranges of seeds, run anywhere.

A *shard* is one configuration's seeds ``[first_seed, first_seed + seeds)``: a ``PaperConfig``
with those two fields set. The random streams are counter-based per experiment and a seed's keys
depend on its index alone (``paper.experiment_keys``), so a shard run alone, in any process, on
any machine, gives each of its experiments exactly the numbers it has inside the full run, and

    concatenate([run_shard(shard) for shard in split(config, k)]) == run_shard(config)

bit for bit, whatever ``k``, the order the shards finish in, the backend or the thread count. The
results of the whole run are then ``paper.summarise`` of the concatenation, the same function one
process uses, so ``results.json`` repeats to the last digit (but for its ``timing``).

A shard's result is its raw per-episode metrics (``[seeds, runs, episodes]`` per world, algorithm
and measure); ``save`` writes it as one ``.npz`` file, atomically, named after the numbers-relevant
config (``digest``) and the seed range, so a finished shard is never run twice.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from factorq_torch.base.keys import EPISODE_METRICS
from factorq_torch.base.validation import check_int
from factorq_trainers.experiments import paper
from factorq_trainers.runner import checkpoint, cluster, kept, reading
from factorq_trainers.runner import results as result_files

#: Config fields that do not change a shard's numbers (tested: backends and thread counts give
#: identical results), left out of its digest so that they may differ between a run and its resume.
NUMBER_FREE_FIELDS = ("out", "threads", "backend", "device", "first_seed", "seeds")
#: Metrics of a shard, per world and algorithm: ``[seeds, runs, episodes]`` each.
METRICS = EPISODE_METRICS
#: Where a sharded run (``factorq paper --cluster``, a paper sweep) keeps its shards in ``--out``.
SHARDS_DIRECTORY = "shards"
#: Seeds per shard of ``factorq paper --cluster`` unless ``--shard-seeds`` says otherwise.
DEFAULT_PAPER_SHARD_SEEDS = 10
SHARD_SUFFIX = ".npz"

#: A shard's result: ``{"world/algorithm/metric": array [seeds, runs, episodes]}``.
ShardMetrics = dict[str, np.ndarray]


def split(config: paper.PaperConfig, shard_seeds: int) -> list[paper.PaperConfig]:
    """``config``'s seeds cut into contiguous shards of ``shard_seeds`` (the last may be smaller).

    >>> [(s.first_seed, s.seeds) for s in split(paper.PaperConfig(seeds=10), 4)]
    [(0, 4), (4, 4), (8, 2)]
    """
    check_int("shard_seeds", shard_seeds, 1)
    stop = config.first_seed + config.seeds
    return [
        replace(config, first_seed=first, seeds=min(shard_seeds, stop - first))
        for first in range(config.first_seed, stop, shard_seeds)
    ]


def run_shard(shard: paper.PaperConfig, threads: int | None = None) -> ShardMetrics:
    """The raw metrics of ``shard``'s experiments, computed here (the task a worker runs).

    ``threads`` overrides ``shard.threads`` (it does not change the numbers). Nothing is written:
    no checkpoint, no results file.
    """
    if threads is not None:
        shard = replace(shard, threads=threads)
    backend = paper.resolve_backend(shard)
    driver = paper.backend_driver(backend)
    # every=None: a Checkpointer that only counts; shards are short and are themselves the unit
    # of resumption.
    counter = checkpoint.Checkpointer(shard.out, paper.config_dict(shard), backend)
    metrics: ShardMetrics = {}
    for algorithm in shard.algorithms:
        keys = paper.experiment_keys(shard, algorithm)
        batch = driver(paper.Job(shard, algorithm, keys, counter.advance, counter))
        for position, world in enumerate(shard.worlds):
            rows = slice(position * shard.seeds, (position + 1) * shard.seeds)
            for name in METRICS:
                metrics[f"{world}/{algorithm}/{name}"] = batch[name][rows].cpu().numpy()
    return metrics


def concatenate(
    config: paper.PaperConfig, parts: list[ShardMetrics]
) -> dict[tuple[str, str], dict[str, np.ndarray]]:
    """The metrics of ``config`` (``paper.summarise``'s input) from its shards' ``parts``, in seed
    order; a ValueError if they do not cover its seeds exactly once."""
    cells: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for world, algorithm in config.cells:
        cells[world, algorithm] = {
            name: np.concatenate([part[f"{world}/{algorithm}/{name}"] for part in parts])
            for name in METRICS
        }
        count = len(cells[world, algorithm][METRICS[0]])
        if count != config.seeds:
            raise ValueError(
                f"the shards hold {count} seeds of {world}/{algorithm}, not {config.seeds}"
            )
    return cells


def results(
    config: paper.PaperConfig, parts: list[ShardMetrics], timing: dict[str, Any]
) -> dict[str, Any]:
    """``results.json`` of ``config`` from its shards (``paper.summarise``), with ``timing``."""
    summary = paper.summarise(config, concatenate(config, parts))
    summary["timing"] = timing
    return summary


# --------------------------------------------------------------------------------------------
# Shard files


def digest(config: paper.PaperConfig) -> str:
    """A short hash of the fields that decide ``config``'s numbers (``NUMBER_FREE_FIELDS`` out)."""
    relevant = {
        key: value
        for key, value in paper.config_dict(config).items()
        if key not in NUMBER_FREE_FIELDS
    }
    text = json.dumps(relevant, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def shard_path(directory: str | os.PathLike, shard: paper.PaperConfig) -> Path:
    """``directory/<digest>/<first>-<stop>.npz``: where ``shard``'s result is kept."""
    stop = shard.first_seed + shard.seeds
    return Path(directory) / digest(shard) / f"{shard.first_seed:06d}-{stop:06d}{SHARD_SUFFIX}"


#: Metrics that count (steps, collisions): whole numbers >= 0; the others need only be finite.
_COUNTS = ("steps", "collisions", "greedy_collisions")


def metrics_digest(metrics: ShardMetrics) -> str:
    """SHA-256 of ``metrics``: every name, dtype, shape and byte, in name order (a kept shard is
    reused on a rerun: an edit to its numbers must not reach the results silently)."""
    hasher = hashlib.sha256()
    for name in sorted(metrics):
        array = np.ascontiguousarray(metrics[name])
        hasher.update(f"{name}:{array.dtype.str}:{array.shape};".encode())
        hasher.update(array.tobytes())
    return hasher.hexdigest()


def _check_metrics(
    path: Path, shard: paper.PaperConfig, metrics: ShardMetrics, stored: str
) -> None:
    """Raise a ValueError naming ``path`` unless ``metrics`` are what ``run_shard(shard)`` gives:
    its digest, every metric of every cell, the shape ``[seeds, runs, episodes]``, finite
    values, counts whole and >= 0 (checked even when the digest matches: it proves integrity,
    not origin)."""
    kept.check_digest(path, "shard file", stored, metrics_digest(metrics))
    remedy = kept.REMEDY
    shape = (shard.seeds, shard.runs, shard.episodes)
    for world in shard.worlds:
        for algorithm in shard.algorithms:
            for name in METRICS:
                key = f"{world}/{algorithm}/{name}"
                values = metrics.get(key)
                if values is None:
                    raise ValueError(f"shard file {path} lacks the metric {key}: {remedy}")
                if values.shape != shape or values.dtype.kind not in "iuf":
                    raise ValueError(
                        f"shard file {path}: {key} is {values.dtype} {list(values.shape)}, "
                        f"not numbers {list(shape)}: {remedy}"
                    )
                bad = ~np.isfinite(values)
                if name in _COUNTS:
                    bad |= (values < 0) | (values != np.floor(values))
                if bad.any():
                    first = values[bad].flat[0]
                    raise ValueError(
                        f"shard file {path}: {key} holds {first}, not a "
                        f"{'count' if name in _COUNTS else 'finite number'}: {remedy}"
                    )


def save(path: str | os.PathLike, shard: paper.PaperConfig, metrics: ShardMetrics) -> None:
    """Write ``metrics`` (with ``shard``'s config and their digest, for checking) to ``path``,
    all or nothing."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    config = json.dumps(paper.config_dict(shard), sort_keys=True)
    digest_of = np.array(metrics_digest(metrics))

    def write(temporary: Path) -> None:
        with open(temporary, "wb") as handle:
            np.savez_compressed(
                handle,
                allow_pickle=False,  # numbers and text only (and no metric can take the name)
                __config__=np.array(config),
                __sha256__=digest_of,
                **metrics,
            )
            handle.flush()
            os.fsync(handle.fileno())

    result_files.write_atomic(path, write)


def load(path: str | os.PathLike, shard: paper.PaperConfig) -> ShardMetrics:
    """The metrics saved at ``path``; a ValueError naming the file if it is not ``shard``'s."""
    # what the shard's metrics take unpacked (8 bytes a value at most), its config and digest
    cells = len(shard.worlds) * len(shard.algorithms) * len(METRICS)
    limit = cells * (shard.seeds * shard.runs * shard.episodes * 8 + 1024) + 2**20
    try:
        data = reading.read_npz(path, "shard file", limit, limit)
        saved = json.loads(str(data["__config__"]))
        stored = str(data["__sha256__"]) if "__sha256__" in data else ""
        metrics = {key: value for key, value in data.items() if not key.startswith("__")}
    except reading.ReadError as error:
        raise ValueError(f"{error}: {kept.REMEDY}") from None
    except (ValueError, KeyError) as error:
        raise ValueError(f"shard file {path} is unreadable ({error}): {kept.REMEDY}") from None
    if not isinstance(saved, dict):  # any JSON may stand there (tests/test_hardening_fuzz.py)
        raise ValueError(f"shard file {path} holds no config: {kept.REMEDY}")
    expected = paper.config_dict(shard)
    differing = sorted(
        key
        for key in expected
        if key not in NUMBER_FREE_FIELDS[:4] and saved.get(key) != expected[key]
    )
    if differing:
        raise ValueError(
            f"shard file {path} holds another config (differs in {', '.join(differing)}): "
            f"{kept.REMEDY}"
        )
    _check_metrics(Path(path), shard, metrics, stored)
    return metrics


# --------------------------------------------------------------------------------------------
# Shards run on an executor, kept in OUT/shards/


def run_shards(
    pending: Sequence[paper.PaperConfig],
    directory: Path,
    executor: cluster.InProcess | cluster.DaskExecutor,
    done: Callable[[paper.PaperConfig], None],
) -> None:
    """Run ``pending`` shards on ``executor``, saving each one's file as soon as it arrives."""
    function: Callable[[paper.PaperConfig], ShardMetrics]
    if isinstance(executor, cluster.DaskExecutor):
        function = functools.partial(run_shard, threads=1)
    else:
        function = run_shard
    names = [f"shard-{digest(s)}-{s.first_seed}-{s.first_seed + s.seeds}" for s in pending]
    for index, metrics in executor.map(function, list(pending), names):
        shard = pending[index]
        save(shard_path(directory, shard), shard, metrics)
        done(shard)


def _missing(
    directory: Path, every: list[paper.PaperConfig], force: bool = False
) -> list[paper.PaperConfig]:
    """The shards of ``every`` to run: those without a kept file, and (``force``) those whose
    kept file fails its checks; without ``force`` such a file is refused before any work."""
    return [
        shard
        for shard in every
        if not kept.reusable(
            shard_path(directory, shard), functools.partial(_load_shard, shard=shard), force
        )
    ]


def _load_shard(path: Path, shard: paper.PaperConfig) -> ShardMetrics:
    return load(path, shard)


def run_paper(
    config: paper.PaperConfig,
    executor: cluster.InProcess | cluster.DaskExecutor,
    shard_seeds: int = DEFAULT_PAPER_SHARD_SEEDS,
    progress: paper.ProgressCallback | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """``paper.run(config)``'s results, computed as shards of ``shard_seeds`` seeds on
    ``executor``, each kept in ``OUT/shards/`` (existing ones are not rerun; one that fails its
    checks is refused, or with ``force`` recomputed). Identical numbers; ``timing`` says where
    and how they were computed."""
    import torch

    started = time.perf_counter()
    directory = Path(config.out) / SHARDS_DIRECTORY
    every = split(config, shard_seeds)
    pending = _missing(directory, every, force)
    per_seed = len(config.cells) * config.runs * config.episodes
    total_seeds = config.seeds
    state = {"seeds": total_seeds - sum(s.seeds for s in pending)}

    def report() -> None:
        if progress is not None:
            progress(
                paper.Progress(
                    state["seeds"] * per_seed,
                    total_seeds * per_seed,
                    state["seeds"] * len(config.cells),
                    total_seeds * len(config.cells),
                )
            )

    def done(shard: paper.PaperConfig) -> None:
        state["seeds"] += shard.seeds
        report()

    report()
    run_shards(pending, directory, executor, done)
    parts = [load(shard_path(directory, shard), shard) for shard in every]
    wall = time.perf_counter() - started
    env_steps = int(
        sum(part[key].sum() for part in parts for key in part if key.endswith("/steps"))
    )
    timing = {
        "wall_s": round(wall, 3),
        "backend": paper.resolve_backend(config),
        "threads": 1  # a worker's, or this process's as paper.run reports it
        if isinstance(executor, cluster.DaskExecutor)
        else config.threads or torch.get_num_threads(),
        "env_steps": env_steps,
        "env_steps_per_s": round(env_steps / max(wall, 1e-9)),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "shards": {
            "where": executor.description,
            "seeds_per_shard": shard_seeds,
            "total": len(every),
            "run_now": len(pending),
        },
    }
    return results(config, parts, timing)
