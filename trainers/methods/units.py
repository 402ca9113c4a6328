"""What several commands' units share around their methods, torch loaded only when a unit runs:
``torch_threads`` (a unit's torch threads, restored after), ``tick`` (progress every 100 env
steps) and ``seed_stat`` (a measure's mean over seeds with its 95% interval)."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import Any

from factorq_trainers.analysis.stats import bootstrap_mean_ci, interval, scalar_ci, wilson_ci


@contextlib.contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """torch's intra-op threads set to ``count`` while the block runs (tiny tensors: more
    threads only wait on each other), the caller's number restored after."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def tick(progress: Callable[[int], None], step: int, total: int) -> None:
    """Report env steps to ``progress`` every 100 steps of ``total``, and the rest at the end."""
    if step % 100 == 0 or step == total:
        progress(100 if step % 100 == 0 else step % 100)


def seed_stat(values: list[float | None], seed: int, proportion: bool = False) -> dict[str, Any]:
    """Mean over the seeds that have a value, its 95% interval (Wilson's for a proportion, the
    BCa bootstrap's otherwise: neither leaves the possible range) and how many seeds have one."""
    present = [v for v in values if v is not None]
    if not present:
        return {"mean": None, "ci95": None, "n": 0}
    method = wilson_ci if proportion else functools.partial(bootstrap_mean_ci, seed=seed)
    mean, low, high = scalar_ci(present, method)
    return {"mean": mean, "ci95": interval(low, high), "n": len(present)}
