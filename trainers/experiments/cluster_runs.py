"""``factorq paper`` and ``factorq compare`` on an executor (``--cluster``, ``--scheduler``):
their options, the executor they ask for, the paper's seeds as shards and compare's methods as
one task each, under one progress bar.
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable
from typing import Any

from factorq_trainers.runner import cluster


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
