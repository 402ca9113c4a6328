"""``factorq paper`` and ``factorq compare`` on an executor (``--cluster``, ``--scheduler``):
their options, the executor they ask for, the paper's seeds as shards and compare's methods as
one task each, under one progress bar.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from collections.abc import Callable
from typing import Any

from factorq_torch.base.validation import INT32_MAX, check_int
from factorq_trainers.experiments import paper
from factorq_trainers.experiments.paper_shards import (
    DEFAULT_PAPER_SHARD_SEEDS,
    SHARDS_DIRECTORY,
    run_paper,
)
from factorq_trainers.runner import cluster


def add_paper_options(parser: argparse.ArgumentParser) -> None:
    """The cluster options of ``factorq paper``: ``cluster.add_options`` and ``--shard-seeds``."""
    cluster.add_options(parser)
    parser.add_argument(
        "--shard-seeds",
        type=int,
        metavar="K",
        help="With --cluster or --scheduler: seeds per shard (the unit of work; finished shards "
        "are kept in OUT/shards/ and not rerun, so a killed run resumes). Same numbers as one "
        f"process. (default: {DEFAULT_PAPER_SHARD_SEEDS})",
        default=argparse.SUPPRESS,
    )


def paper_executor(args: argparse.Namespace) -> cluster.InProcess | cluster.DaskExecutor | None:
    """The executor ``factorq paper``'s options ask for: ``None`` for the usual in-process run,
    else an open one (a ``ValueError`` in one line when it cannot be had)."""
    names = ("cluster", "scheduler", "connect_timeout", "worker_timeout", "shard_seeds")
    if not any(hasattr(args, name) for name in names):
        return None
    for name in ("checkpoint_every", "resume"):
        if hasattr(args, name):
            option = "--" + name.replace("_", "-")
            raise ValueError(
                f"{option} does not apply to a sharded run: its finished shards, kept in "
                f"OUT/{SHARDS_DIRECTORY}/, are what a rerun resumes from (leave {option} out)"
            )
    check_int(
        "--shard-seeds", getattr(args, "shard_seeds", DEFAULT_PAPER_SHARD_SEEDS), 1, INT32_MAX
    )
    return cluster.executor_from_args(args) or cluster.InProcess()


def run_paper_on(
    executor: cluster.InProcess | cluster.DaskExecutor,
    config: paper.PaperConfig,
    args: argparse.Namespace,
    progress: paper.ProgressCallback | None = None,
) -> dict[str, Any]:
    """``run_paper`` with ``args.shard_seeds``, closing ``executor`` afterwards."""
    try:
        shard_seeds = getattr(args, "shard_seeds", DEFAULT_PAPER_SHARD_SEEDS)
        return run_paper(config, executor, shard_seeds, progress, hasattr(args, "force"))
    finally:
        executor.close()


def run_compare_on(
    executor: cluster.InProcess | cluster.DaskExecutor,
    config: Any,
    run_method: Callable[..., dict[str, Any]],
    summarise: Callable[[Any, dict[str, Any]], dict[str, Any]],
) -> dict[str, Any]:
    """``factorq compare`` with one task per method on ``executor`` (closed afterwards): a
    method's batch is the unit, so every method, DQN included, repeats its in-process numbers.
    ``run_method`` and ``summarise`` are ``factorq_trainers.experiments.compare``'s (passed in: this
    module does not import it). Seeds are not sharded: DQN's seeds share a random stream within
    their batch."""
    started = time.perf_counter()
    methods = list(config.methods)
    bar = ShardBar("factorq compare", "method")
    try:
        bar(0, len(methods))
        function = functools.partial(_compare_method, run_method, config)
        runs: dict[str, Any] = {}
        for index, result in executor.map(function, methods, [f"compare-{m}" for m in methods]):
            runs[methods[index]] = result
            bar(len(runs), len(methods))
        bar.close()
        where = executor.description
    finally:
        executor.close()
    results = summarise(config, {method: runs[method] for method in methods})
    results["timing"] = {"wall_s": round(time.perf_counter() - started, 3), "where": where}
    return results


class ShardBar:
    """A tqdm bar of shards (or other tasks) done, with the time left."""

    def __init__(self, description: str = "factorq sweep", unit: str = "shard") -> None:
        self.bar: Any = None  # a tqdm bar once the first count arrives (tqdm: untyped)
        self.description = description
        self.unit = unit

    def __call__(self, done: int, total: int) -> None:
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(
                total=total,
                initial=done,
                desc=self.description,
                unit=self.unit,
                dynamic_ncols=True,
                mininterval=0.5 if sys.stderr.isatty() else 30.0,
                file=sys.stderr,
            )
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _compare_method(run_method: Callable[..., Any], config: Any, method: str) -> Any:
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        return run_method(config, method)
    finally:
        torch.set_num_threads(threads)
