"""``factorq paper``'s drivers: which backend runs (``resolve_backend``, the fall-back notice,
threads and processes), each algorithm's experiments (a ``Job`` with its ``BatchKeys``) on the
compiled fast path or the modular torchrl path, and the modular path's algorithms side by side
in child processes."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np
import torch

from factorq_envs.regimes import REGIME_PERIODS
from factorq_torch.base.config import ALGORITHMS
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD
from factorq_trainers.experiments import experiment
from factorq_trainers.experiments import paper_processes as processes
from factorq_trainers.experiments.paper_config import PaperConfig, config_dict
from factorq_trainers.runner import checkpoint, resources
from factorq_trainers.runner.resume_checks import check_state


def resolve_backend(config: PaperConfig, world: Any = None) -> str:
    """The backend ``run`` will use: ``"fast"`` or ``"modular"``.

    This is the one place where the backend is chosen. ``auto`` takes the compiled fast path when
    it is available on this machine, the device is the cpu and the kernel can run the world
    (``fast.unsupported_reason``: a body past its limits, or ``world``, an
    ``factorq_envs.protocol.World`` other than the paper's grid), the modular torchrl path
    otherwise.
    """
    from factorq_trainers.compiled import fast

    on_cpu = torch.device(config.device).type == "cpu"
    if config.backend == "fast" and not fast.is_available():
        raise ValueError(f"backend='fast' is unavailable here: {fast.unavailable_reason()}")
    unsupported = fast.unsupported_reason(config.world if world is None else world)
    if config.backend == "fast" and unsupported is not None:
        raise ValueError(f"backend='fast' cannot run this config: {unsupported}")
    if config.backend == "auto":
        usable = on_cpu and fast.is_available() and unsupported is None
        return "fast" if usable else "modular"
    return config.backend


#: Seconds of the modular path per (algorithm, run, episode) of the default batch, measured on
#: a 2-core CPU: one run of each algorithm (``--backend modular --runs 1``) took 68 s there, so
#: about 11 min with the algorithms one after the other (``--threads 1``; docs/decisions.md).
MODULAR_SECONDS_PER_EPISODE = 68.0 / (2 * 1 * 200)
#: Wall seconds of the modular path per (run, episode) of the default batch with each algorithm
#: in its own process (``modular_processes``), measured on the same 2-core CPU with nothing
#: else running: the defaults (``--backend modular``, 10 runs x 200 episodes) took 286.2 s and
#: 286.9 s, Q-learning the slower of the two (its batch needs 230,896 batched steps, Factor-Q's
#: 131,591; docs/decisions.md).
MODULAR_PARALLEL_SECONDS_PER_EPISODE = 286.5 / (10 * 200)
#: Memory of one child process of the modular path besides its batch: the interpreter with torch
#: and torchrl imported (329 MiB peak resident set measured; counted in ``run``'s check).
PROCESS_BYTES = 330 * 2**20


def fallback_notice(
    config: PaperConfig, backend: str, world: Any = None, process_count: int | None = None
) -> str | None:
    """The one-line notice of ``auto`` falling back to the modular path: why, about how long the
    run will take (on ``process_count`` processes, default ``modular_processes(config, world)``),
    how to get the fast path (None when nothing fell back)."""
    from factorq_trainers.compiled import fast

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
    if process_count is None:
        process_count = modular_processes(config, world)
    if process_count > 1:  # the algorithms side by side: about the slower one's time
        estimate = MODULAR_PARALLEL_SECONDS_PER_EPISODE * config.runs * config.episodes
    else:
        estimate = (
            MODULAR_SECONDS_PER_EPISODE * len(config.algorithms) * config.runs * config.episodes
        )
    duration = f"{estimate / 60:.0f} min" if estimate >= 90 else f"{max(estimate, 1):.0f} s"
    return (
        f"factorq: the compiled fast path is unavailable ({fast.unavailable_reason()}): running "
        f"on the modular torchrl path, roughly {duration} on a 2-core CPU rather than "
        f"seconds. For the fast path install a C compiler (cc, gcc or clang; e.g. "
        f"`apt-get install gcc`) or point FACTORQ_CC at one, then run again."
    )


def threads_used(config: PaperConfig, backend: str, process_count: int = 1) -> int:
    """CPU threads the experiment actually runs on: the fast path's workers (at most one per
    experiment), or the modular path's torch intra-op threads (1 unless --threads says more) in
    each of its ``process_count`` processes (``modular_processes``; ``modular_threads`` each)."""
    if backend == "fast":
        threads = config.threads if config.threads is not None else torch.get_num_threads()
        return max(1, min(threads, len(config.worlds) * config.seeds))
    return process_count * modular_threads(config, process_count)


def modular_processes(config: PaperConfig, world: Any = None, checkpointing: bool = False) -> int:
    """Processes the modular path runs ``config``'s algorithms in: one per algorithm, all at once,
    where two or more CPU threads are allowed (``config.threads``, default torch's thread count,
    what the fast path takes); 1 (this process, one algorithm after the other) with a single
    algorithm or thread, with another ``world`` than the grid, with ``checkpointing`` (a
    checkpoint holds the state of one running algorithm) or where no process can be started.
    ``run`` also falls back to 1 if the processes' memory does not fit."""
    if len(config.algorithms) < 2 or world is not None or checkpointing:
        return 1
    if not processes.available():  # no Python to start them with (a frozen program)
        return 1
    allowed = config.threads if config.threads is not None else torch.get_num_threads()
    return len(config.algorithms) if allowed >= 2 else 1


def modular_threads(config: PaperConfig, process_count: int) -> int:
    """Torch intra-op threads of each of the modular path's ``process_count`` processes: 1 (the
    per-step tensors are small: more threads only synchronise) unless ``config.threads`` gives
    each more."""
    return max(1, (config.threads or 1) // process_count)


class BatchKeys(NamedTuple):
    """One algorithm's experiments, world-major and seed-minor: ``[W * S]`` each."""

    periods: torch.Tensor
    world_keys: torch.Tensor
    policy_keys: torch.Tensor


class Job(NamedTuple):
    """One algorithm's experiments, as a backend driver runs them."""

    config: PaperConfig
    algorithm: str
    keys: BatchKeys
    #: ``report(episodes, experiments)``: episodes and experiments completed since its last call.
    report: Callable[[int, int], None]
    #: Restores a resumed state (``restore``) and saves when due (``due``, ``save``).
    checkpoints: checkpoint.Checkpointer
    #: The world the experiments run in: ``None`` for the config's grid, else an
    #: ``factorq_envs.protocol.World`` (modular path only).
    world: Any = None


def experiment_keys(config: PaperConfig, algorithm: str) -> BatchKeys:
    """Obstacle periods, world keys and policy keys ``[W * S]`` of one algorithm's experiments.

    Experiments are ordered world-major (``config.worlds``), seed-minor. The key of seed index
    ``i`` (row ``i - config.first_seed``) in world ``w`` (index in ``REGIMES``) does not depend on
    what else is selected, so seeds ``[a, b)`` run alone draw what they draw in a larger run.
    """
    seeds = range(config.first_seed, config.first_seed + config.seeds)
    labels = [(world, index) for world in config.worlds for index in seeds]
    periods = torch.tensor([REGIME_PERIODS[world] for world, _ in labels])  # [W * S]
    world_keys = experiment.experiment_keys(config.seed, STREAM_WORLD, labels)
    policy_keys = experiment.experiment_keys(
        config.seed, STREAM_POLICY, labels, ALGORITHMS, algorithm
    )
    return BatchKeys(periods, world_keys, policy_keys)


def _run_fast(job: Job) -> dict[str, torch.Tensor]:
    """One algorithm's experiments on the compiled fast path, in chunks (progress, Ctrl-C,
    checkpoints)."""
    from factorq_trainers.compiled.fast import ExperimentBatch

    config, algorithm, (periods, world_keys, policy_keys), report, checkpoints, _ = job

    batch = ExperimentBatch(
        algorithm,
        periods,
        config.world,
        config.agent,
        config.runs,
        config.episodes,
        world_keys,
        policy_keys,
        threads=config.threads,
    )
    fresh = batch.state_dict()

    def load_state(state: dict[str, Any]) -> None:
        check_state(state, fresh, config, periods)  # before anything reaches the kernel
        batch.load_state_dict(state)

    checkpoints.restore(algorithm, load_state)
    finished = batch.experiments_finished
    # Chunks of about a quarter of a second keep the progress bar alive, Ctrl-C prompt and
    # checkpoints on time; results do not depend on the chunking.
    chunk = 1_000
    while not batch.done:
        started = time.perf_counter()
        completed = batch.advance(chunk)
        elapsed = time.perf_counter() - started
        now_finished = batch.experiments_finished
        report(completed, now_finished - finished)
        finished = now_finished
        if checkpoints.due() and not batch.done:
            checkpoints.save(algorithm, batch.state_dict())
        chunk = int(min(max(chunk * 0.25 / max(elapsed, 1e-3), 100), 1_000_000))
    return batch.metrics()


def _run_modular(job: Job) -> dict[str, torch.Tensor]:
    """One algorithm's experiments on the modular torchrl path (env, tables, policy, loss,
    ``OnlineCollector``): the fallback where no C compiler is available, and the reference the
    fast path is tested against. Same keys, so the same numbers as ``_run_fast``."""
    from factorq_torch.collectors import OnlineCollector

    config, algorithm, (periods, world_keys, policy_keys), report, checkpoints, world = job

    device = torch.device(config.device)
    world = config.world if world is None else world
    grid = experiment.make_env(world, periods, world_keys, device=device)
    task, local = experiment.tabular_values(algorithm, len(periods), world, device)
    env, policy, loss = experiment.online_agent(
        grid, task, local, config.agent, policy_keys, device=device
    )
    collector = OnlineCollector(
        env, policy, loss, runs=config.runs, episodes=config.episodes, progress=report
    )

    fresh = {
        "collector": checkpoint.to_device(collector.state_dict(), torch.device("cpu")),
        "world_state": checkpoint.to_device(grid.world_state._asdict(), torch.device("cpu")),
    }
    # A new collector has not stepped: its observation is None; a saved one is checked by
    # _check_observation (its entries depend on the body, the env and the policy).

    def load_state(state: dict[str, Any]) -> None:
        check_state(state, fresh, config, periods)
        collector.load_state_dict(checkpoint.to_device(state["collector"], device))
        saved = state["world_state"]
        for name, tensor in grid.world_state._asdict().items():
            if saved[name].shape != tensor.shape or saved[name].dtype != tensor.dtype:
                raise ValueError(f"world_state[{name!r}] does not fit this batch")
        grid.world_state = type(grid.world_state)(**checkpoint.to_device(saved, device))

    checkpoints.restore(algorithm, load_state)
    # The per-step tensors are small: intra-op threads only add synchronisation (2 threads were
    # measured 2x slower than 1 here), so the modular path uses one unless --threads says more.
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(config.threads or 1)
    try:
        while not collector.done:
            collector.step()
            if checkpoints.due() and not collector.done:
                state = {
                    "collector": collector.state_dict(),
                    "world_state": grid.world_state._asdict(),
                }
                checkpoints.save(algorithm, checkpoint.to_device(state, torch.device("cpu")))
    finally:
        torch.set_num_threads(previous_threads)
    return dict(collector.metrics.items())


def _modular_in_process(config: PaperConfig, algorithm: str, report: Any) -> dict[str, np.ndarray]:
    """What each child process of a parallel modular run does (``_run_side_by_side``): one
    algorithm's experiments on the modular path, without checkpoints (a Checkpointer that only
    counts), their metrics as numpy arrays (they pickle as plain bytes)."""
    counter = checkpoint.Checkpointer(config.out, config_dict(config), "modular")
    job = Job(config, algorithm, experiment_keys(config, algorithm), report, counter)
    return {name: values.cpu().numpy() for name, values in _run_modular(job).items()}


def backend_driver(backend: str) -> Callable[[Job], dict[str, torch.Tensor]]:
    """The function that runs one algorithm's experiments (a ``Job``) on ``backend`` and returns
    their metrics, ``ExperimentBatch.metrics()`` (``[W * S, runs, episodes]`` each)."""
    return _run_fast if backend == "fast" else _run_modular


def _run_side_by_side(
    config: PaperConfig,
    count: int,
    checkpoints: checkpoint.Checkpointer,
    advance_progress: Callable[[int, int], None],
) -> None:
    """Every algorithm's experiments on the modular path at once, into ``checkpoints.finish``:
    the first in this process, the others each in a child process (``processes.Children``),
    with ``modular_threads`` torch threads each. A child's start-up (mostly importing torch,
    about 3.5 s) overlaps with this process's work and delays only its own algorithm."""
    config = replace(config, threads=modular_threads(config, count))
    first, *others = config.algorithms
    items = {algorithm: (config, algorithm) for algorithm in others}
    with processes.Children(_modular_in_process, items, advance_progress) as children:

        def report(episodes: int, experiments: int) -> None:
            advance_progress(episodes, experiments)
            children.poll(every=processes.PROGRESS_SECONDS)  # their progress, errors, deaths

        keys = experiment_keys(config, first)
        checkpoints.finish(first, _run_modular(Job(config, first, keys, report, checkpoints)))
        computed = children.wait()
    for algorithm, arrays in computed.items():
        checkpoints.finish(algorithm, {name: torch.from_numpy(a) for name, a in arrays.items()})


def _processes_fit(config: PaperConfig, count: int) -> bool:
    """Whether the modular path's ``count`` processes fit in the memory available: every
    algorithm's tables and state at once (``resources.paper_estimate`` of each alone) and
    ``PROCESS_BYTES`` for each child, besides this process's metrics and curves."""
    available, _ = resources.available_memory()
    if available is None:
        return True
    alone = [
        resources.paper_estimate(replace(config, algorithms=(algorithm,)))
        for algorithm in config.algorithms
    ]
    batches = sum(estimate.parts["tables"] + estimate.parts["run state"] for estimate in alone)
    whole = resources.paper_estimate(config)
    rest = whole.bytes - whole.parts["tables"] - whole.parts["run state"]
    return batches + (count - 1) * PROCESS_BYTES + rest <= available
