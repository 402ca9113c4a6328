"""``factorq paper``'s drivers: which backend runs (``resolve_backend``, the fall-back notice,
threads and processes) and one algorithm's experiments (their ``BatchKeys``) on the compiled
fast path or the modular torchrl path."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import torch

from factorq_envs.regimes import REGIME_PERIODS
from factorq_torch.base.config import ALGORITHMS
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.compiled import fast
from factorq_trainers.methods import experiment
from factorq_trainers.methods.units import torch_threads

#: ``report(episodes)``: episodes completed since its last call.
Report = Callable[[int], None]


def resolve_backend(config: PaperConfig, world: Any = None) -> str:
    """The backend ``run`` will use, ``"fast"`` or ``"modular"`` (the one place it is chosen):
    ``auto`` takes the compiled path where it is available, the device is the cpu and the kernel
    can run the world (``fast.unsupported_reason``: a body past its limits, or ``world``, another
    ``factorq_envs.protocol.World`` than the grid), else the modular torchrl path."""
    on_cpu = torch.device(config.device).type == "cpu"
    if config.backend == "fast" and not fast.is_available():
        raise ValueError(f"backend='fast' is unavailable here: {fast.unavailable_reason()}")
    unsupported = fast.unsupported_reason(config.world if world is None else world)
    if config.backend == "fast" and unsupported is not None:
        raise ValueError(f"backend='fast' cannot run this config: {unsupported}")
    if config.backend == "auto":
        return "fast" if on_cpu and fast.is_available() and unsupported is None else "modular"
    return config.backend


#: Seconds of the modular path per (algorithm, run, episode) of the default batch, measured on
#: a 2-core CPU: one run of each algorithm (``--backend modular --runs 1``) took 68 s there, so
#: about 11 min with the algorithms one after the other (``--threads 1``; docs/decisions.md).
MODULAR_SECONDS_PER_EPISODE = 68.0 / (2 * 1 * 200)


def fallback_notice(
    config: PaperConfig, backend: str, workers: int = 1, world: Any = None
) -> str | None:
    """The one-line notice of ``auto`` falling back to the modular path: why (``world``: another
    world than the grid, ``paper.run``'s), about how long the run will take (its units on
    ``workers`` processes), how to get the fast path (None when nothing fell back)."""
    if backend != "modular" or config.backend != "auto":
        return None
    unsupported = fast.unsupported_reason(config.world if world is None else world)
    if unsupported is not None:  # the one-line notice of a fall-back
        return (
            f"factorq: the fast path cannot run this config ({unsupported}): running on "
            f"the modular torchrl path"
        )
    if torch.device(config.device).type != "cpu":
        return None  # asked for: a device the compiled path does not run on
    estimate = (
        MODULAR_SECONDS_PER_EPISODE
        * len(config.methods)
        * config.runs
        * config.episodes
        / max(1, min(workers, len(config.methods)))
    )
    duration = f"{estimate / 60:.0f} min" if estimate >= 90 else f"{max(estimate, 1):.0f} s"
    return (
        f"factorq: the compiled fast path is unavailable ({fast.unavailable_reason()}): running "
        f"on the modular torchrl path, roughly {duration} on a 2-core CPU rather than "
        f"seconds. For the fast path install a C compiler (cc, gcc or clang; e.g. "
        f"`apt-get install gcc`) or point FACTORQ_CC at one, then run again."
    )


def threads_for(config: PaperConfig, count: int) -> int:
    """``--threads`` (default: the cores torch sees) for ``count`` things that run at once (the
    fast path's experiments, the modular path's processes): at most ``count``, at least 1."""
    threads = config.threads if config.threads is not None else torch.get_num_threads()
    return max(1, min(threads, count))


def threads_used(config: PaperConfig, backend: str) -> int:
    """CPU threads one unit runs on: the fast path's workers (at most one per experiment), or
    the modular path's torch intra-op threads (1 unless --threads says more)."""
    if backend == "fast":
        return threads_for(config, len(config.regimes) * config.seeds)
    return config.threads or 1


class BatchKeys(NamedTuple):
    """One algorithm's experiments, world-major and seed-minor: ``[W * S]`` each."""

    periods: torch.Tensor
    world_keys: torch.Tensor
    policy_keys: torch.Tensor


def experiment_keys(config: PaperConfig, algorithm: str) -> BatchKeys:
    """Obstacle periods, world keys and policy keys ``[W * S]`` of one algorithm's experiments,
    world-major (``config.regimes``), seed-minor: the keys of ``paper.command``'s docstring, the
    same whatever else is selected."""
    seeds = range(config.first_seed, config.first_seed + config.seeds)
    labels = [(world, index) for world in config.regimes for index in seeds]
    periods = torch.tensor([REGIME_PERIODS[world] for world, _ in labels])  # [W * S]
    world_keys = experiment.experiment_keys(config.seed, STREAM_WORLD, labels)
    policy_keys = experiment.experiment_keys(
        config.seed, STREAM_POLICY, labels, ALGORITHMS, algorithm
    )
    return BatchKeys(periods, world_keys, policy_keys)


def run_fast(
    config: PaperConfig, algorithm: str, keys: BatchKeys, report: Report
) -> dict[str, torch.Tensor]:
    """One algorithm's experiments on the compiled fast path, in chunks of about a quarter of a
    second (progress, Ctrl-C; the numbers do not depend on the chunking)."""
    batch = fast.ExperimentBatch(
        algorithm,
        keys.periods,
        config.world,
        config.agent,
        config.runs,
        config.episodes,
        keys.world_keys,
        keys.policy_keys,
        threads=config.threads,
    )
    chunk = 1_000
    while not batch.done:
        started = time.perf_counter()
        report(batch.advance(chunk))
        elapsed = time.perf_counter() - started
        chunk = int(min(max(chunk * 0.25 / max(elapsed, 1e-3), 100), 1_000_000))
    return batch.metrics()


def run_modular(
    config: PaperConfig, algorithm: str, keys: BatchKeys, report: Report, world: Any = None
) -> dict[str, torch.Tensor]:
    """One algorithm's experiments on the modular torchrl path (env, tables, policy, loss,
    ``OnlineCollector``): the fallback where no C compiler is available, the path of a ``world``
    other than the grid, and the reference the fast path is tested against. Same keys, so the
    same numbers as ``run_fast``."""
    from factorq_torch.collectors import OnlineCollector

    device = torch.device(config.device)
    world = config.world if world is None else world
    grid = experiment.make_env(world, keys.periods, keys.world_keys, device=device)
    task, local = experiment.tabular_values(algorithm, len(keys.periods), world, device)
    env, policy, loss = experiment.online_agent(
        grid, task, local, config.agent, keys.policy_keys, device=device
    )
    collector = OnlineCollector(
        env, policy, loss, runs=config.runs, episodes=config.episodes,
        progress=lambda episodes, _experiments: report(episodes),
    )  # fmt: skip
    # The per-step tensors are small: intra-op threads only add synchronisation (2 threads were
    # measured 2x slower than 1 here), so the modular path uses one unless --threads says more.
    with torch_threads(config.threads or 1):
        while not collector.done:
            collector.step()
    return dict(collector.metrics.items())
