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
from dataclasses import asdict, dataclass, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from factorq_envs.world import WORLD_PERIODS, WORLDS, WorldConfig
from factorq_torch.base.config import ALGORITHMS, AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD
from factorq_torch.base.validation import (
    INT32_MAX,
    check_device,
    check_int,
    check_names,
    check_threads,
)
from factorq_trainers.analysis import stats
from factorq_trainers.analysis.claims import compute_claims
from factorq_trainers.analysis.stats import interval, mean_ci
from factorq_trainers.distributed import processes
from factorq_trainers.experiments import experiment
from factorq_trainers.experiments.experiment import (
    MAX_SEED,
    body_options,
    check_qlearning_table,
    check_world_options,
)
from factorq_trainers.runner import checkpoint, resources
from factorq_trainers.runner.options import option
from factorq_trainers.runner.results import SCHEMA_VERSION, software_versions
from factorq_trainers.runner.resume_checks import DRIVERS, check_checkpoint, check_state
from factorq_trainers.runner.schema import CURVE_NAMES

#: Experiment drivers: the compiled kernel, the modular torchrl path, or the first available.
BACKENDS = ("auto", *DRIVERS)
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


@dataclass(frozen=True)
class PaperConfig(experiment.WorldOptions):
    """The paper's experiment (SPEC section 4); defaults reproduce it with 100 seeds."""

    seed: int = option(0, "Master seed: every random number of the experiment derives from it.")
    seeds: int = option(
        100, "Independent experiments per cell (world x algorithm); CIs are across them."
    )
    first_seed: int = option(
        0, "Index of the first seed: a run of seeds first_seed .. first_seed + seeds - 1 (a shard)."
    )
    runs: int = option(
        10, "Runs per experiment (task tables reset each run; Factor-Q's local tables carry over)."
    )
    episodes: int = option(200, "Episodes per run.")
    worlds: tuple[str, ...] = option(
        WORLDS, "Worlds to run: static, semi-dynamic, dynamic (comma-separated)."
    )
    algorithms: tuple[str, ...] = option(
        ALGORITHMS, "Algorithms to run: q-learning, factor-q (comma-separated)."
    )
    epsilon: float = option(0.01, "Probability of a uniformly random (exploratory) action.")
    gamma: float = option(0.9, "Discount of future reward, in [0, 1).")
    alpha: float = option(0.2, "Task learning rate (eqs. 1 and 4), in (0, 1].")
    eta: float = option(0.1, "Margin by which scaled local reward dominates task reward (eq. 3).")
    g_min: float = option(0.01, "Floor of the normaliser G (eq. 3), > 0.")
    out: str = option("results/paper", "Directory for results.json, figure3.png and report.md.")
    threads: int | None = option(
        None,
        "CPU threads for the experiments (default: all available, the compiled path's workers; the "
        "modular path runs 1 torch thread per process, fastest for its small tensors); results do "
        "not depend on it.",
    )
    backend: str = option(
        "auto",
        "Experiment driver: fast (compiled), modular (torchrl), auto (fast if it is available).",
        choices=BACKENDS,
    )
    device: str = option("cpu", "Torch device (the fast backend runs on cpu only).")

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, MAX_SEED)
        check_int("seeds", self.seeds, 1, INT32_MAX)
        check_int("first_seed", self.first_seed, 0, INT32_MAX)
        check_int("runs", self.runs, 1, INT32_MAX)
        check_int("episodes", self.episodes, 1, INT32_MAX)
        object.__setattr__(self, "worlds", check_names("worlds", self.worlds, WORLDS))
        world = check_world_options(
            self.size,
            self.obstacles,
            self.max_steps,
            self.layout_seed,
            self.worlds,
            body_options(self),
        )
        object.__setattr__(
            self, "algorithms", check_names("algorithms", self.algorithms, ALGORITHMS)
        )
        _ = self.agent  # AgentConfig validates epsilon, gamma, alpha, eta and g_min
        if "q-learning" in self.algorithms:  # its state holds the pattern of all sensors
            check_qlearning_table(world)
        if self.threads is not None:
            check_threads("threads", self.threads)
        if self.backend not in BACKENDS:
            raise ValueError(f"backend={self.backend!r} is unknown: choose one of {BACKENDS}")
        try:
            kind = torch.device(self.device).type
        except (RuntimeError, TypeError):
            kind = None  # check_device says why
        if self.backend == "fast" and kind not in (None, "cpu"):
            raise ValueError(f"device={self.device!r} is not supported by backend 'fast' (cpu)")
        # The device must exist here: refused now, not once the run began.
        check_device("device", self.device, allow_meta=False, optional=False)
        if not isinstance(self.out, str | os.PathLike) or not str(self.out):
            raise ValueError(f"out={self.out!r} must be a directory path")
        object.__setattr__(self, "out", str(self.out))
        if Path(self.out).exists() and not Path(self.out).is_dir():
            raise ValueError(f"out={self.out!r} is an existing file: give a directory")

    @property
    def agent(self) -> AgentConfig:
        """The learning parameters, validated."""
        return AgentConfig(
            epsilon=self.epsilon, gamma=self.gamma, alpha=self.alpha, eta=self.eta, g_min=self.g_min
        )

    @property
    def world(self) -> WorldConfig:
        """The world of every experiment; the obstacle period is set per experiment."""
        return check_world_options(
            self.size, self.obstacles, self.max_steps, self.layout_seed, (), body_options(self)
        )

    @property
    def cells(self) -> list[tuple[str, str]]:
        """The selected ``(world, algorithm)`` cells, in canonical order."""
        return [(world, algorithm) for world in self.worlds for algorithm in self.algorithms]


# --------------------------------------------------------------------------------------------
# Running the experiments


CONFIG = PaperConfig


class Progress(NamedTuple):
    """What ``run`` reports to its ``progress`` callback after every chunk of work."""

    episodes_completed: int
    episodes_total: int
    experiments_finished: int
    experiments_total: int


ProgressCallback = Callable[[Progress], None]


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
#: Seconds between two calls of ``run``'s ``progress``, at most (a bar needs no more).
PROGRESS_SECONDS = 0.1
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
    ``i`` (row ``i - config.first_seed``) in world ``w`` (index in ``WORLDS``) does not depend on
    what else is selected, so seeds ``[a, b)`` run alone draw what they draw in a larger run.
    """
    seeds = range(config.first_seed, config.first_seed + config.seeds)
    labels = [(world, index) for world in config.worlds for index in seeds]
    periods = torch.tensor([WORLD_PERIODS[world] for world, _ in labels])  # [W * S]
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


def _check_foreign_world(world: Any, checkpoint_every: Any, resume: Any) -> None:
    """Refuse a ``world`` that ``run`` cannot take: one error naming it."""
    from factorq_envs.protocol import check_world
    from factorq_envs.world import FactoredGrid

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
    fields_ = asdict(config) if is_dataclass(config) else {}
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
            "obstacle_period": WORLD_PERIODS[world],
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


def config_dict(config: PaperConfig) -> dict[str, Any]:
    """Every field of ``config``, JSON-ready (tuples as lists)."""
    return {
        key: list(value) if isinstance(value, tuple) else value
        for key, value in asdict(config).items()
    }


def config_from_dict(data: dict[str, Any]) -> PaperConfig:
    """The inverse of ``config_dict`` (unknown keys are an error)."""
    known = {item.name for item in fields(PaperConfig)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"unknown config fields: {', '.join(unknown)}")
    return PaperConfig(
        **{key: tuple(value) if isinstance(value, list) else value for key, value in data.items()}
    )
