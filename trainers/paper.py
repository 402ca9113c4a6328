"""The paper's experiment (SPEC section 4) and its claims (SPEC section 5): config -> results.

One *experiment* is one world x one algorithm: ``runs`` runs of ``episodes`` episodes. We run
``seeds`` independent experiments per cell of the paper's table and summarise them across seeds:

    config -> keys per experiment -> one batch per algorithm (all worlds, all seeds) -> metrics
           -> per-seed means and per-episode curves -> claims C1-C5 -> results (a JSON-ready dict)

Keys make experiment ``(seed index i, world w, algorithm a)`` draw the same numbers whatever else is
selected: its world key is number ``3 i + w`` of the world stream (shared by both algorithms:
common random numbers) and its policy key number ``2 (3 i + w) + a`` of the policy stream.

Confidence intervals (95%, across seeds; every seed is one independent experiment):

- a mean (a cell's measure, a point of a curve): Student's t interval,
  ``mean +- t(0.975, S - 1) * sd / sqrt(S)``;
- a claim's statistic (a ratio of means, its minimum or maximum over worlds): percentile bootstrap
  over seeds, ``BOOTSTRAP_RESAMPLES`` resamples of the seed indices, paired across cells (the
  cells of one seed index share their world's random numbers), drawn from a generator seeded with
  ``config.seed``, so the intervals are as reproducible as the rest.

With a single seed there is no interval (``null``).
"""

from __future__ import annotations

import ast
import inspect
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from importlib import metadata
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from envs.world import WORLD_PERIODS, WORLDS, WorldConfig, static_layout
from factorq_torch.base.config import ALGORITHMS, AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
from factorq_torch.base.validation import check_int, check_names
from trainers import checkpoint

#: The paper's three worlds and their obstacle periods (SPEC section 1), in canonical order; a
#: world's index here is part of its experiments' keys.
BACKENDS = ("auto", "fast", "modular")
MEASURES = ("total_steps", "collisions", "greedy_collisions")
CURVES = ("steps", "collisions", "greedy_collisions")
MEASURE_LABELS = {
    "total_steps": "total steps",
    "collisions": "collisions",
    "greedy_collisions": "greedy collisions",
}
ALGORITHM_LABELS = {"q-learning": "Q-learning", "factor-q": "Factor-Q"}
BOOTSTRAP_RESAMPLES = 10_000
CONFIDENCE = 0.95
RESULTS_FILE = "results.json"
FIGURE_FILE = "figure3.png"
REPORT_FILE = "report.md"
_MAX_SEED = 2**63 - 1


@dataclass(frozen=True)
class PaperConfig:
    """The paper's experiment (SPEC section 4); defaults reproduce it with 100 seeds."""

    seed: int = 0
    """Master seed: every random number of the experiment derives from it."""
    seeds: int = 100
    """Independent experiments per cell (world x algorithm); CIs are across them."""
    runs: int = 10
    """Runs per experiment (task tables reset each run; Factor-Q's local tables carry over)."""
    episodes: int = 200
    """Episodes per run."""
    size: int = 10
    """Side of the square grid, in cells."""
    obstacles: int = 10
    """Number of single-cell obstacles."""
    worlds: tuple[str, ...] = WORLDS
    """Worlds to run: static, semi-dynamic, dynamic (comma-separated)."""
    algorithms: tuple[str, ...] = ALGORITHMS
    """Algorithms to run: q-learning, factor-q (comma-separated)."""
    max_steps: int = 10_000
    """Actions after which an episode is truncated."""
    layout_seed: int = 0
    """Seed of the static world's obstacle layout."""
    epsilon: float = 0.01
    """Probability of a uniformly random (exploratory) action."""
    gamma: float = 0.9
    """Discount of future reward, in [0, 1)."""
    alpha: float = 0.2
    """Task learning rate (eqs. 1 and 4), in (0, 1]."""
    eta: float = 0.1
    """Margin by which scaled local reward dominates task reward (eq. 3)."""
    g_min: float = 0.01
    """Floor of the normaliser G (eq. 3), > 0."""
    out: str = "results/paper"
    """Directory for results.json, figure3.png and report.md."""
    threads: int | None = None
    """CPU threads for the experiments (default: all available); results do not depend on it."""
    backend: str = "auto"
    """Experiment driver: fast (compiled), modular (torchrl), auto (fast if it is available)."""
    device: str = "cpu"
    """Torch device (the fast backend runs on cpu only)."""
    body: str = "translate"
    """Agent body: translate (the paper: moves N/W/S/E) or heading (forward, turn left/right)."""
    sensors: str = "cross"
    """Sensor layout: cross (the paper: 4 neighbours) or ring (8 neighbours)."""
    distractors: int = 0
    """Extra sensor bits that carry no information (fresh fair coins at every observation)."""
    sensor_permutation: int | None = None
    """Seed of a random order in which the agent receives its sensors (default: layout order)."""
    sensor_noise: float = 0.0
    """Probability that each sensor bit is flipped at each observation, in [0, 1]."""
    actuator_noise: float = 0.0
    """Probability that another actuator fires than the chosen one, in [0, 1]."""

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, _MAX_SEED)
        check_int("seeds", self.seeds, 1)
        check_int("runs", self.runs, 1)
        check_int("episodes", self.episodes, 1)
        check_int("max_steps", self.max_steps, 1)
        check_int("layout_seed", self.layout_seed, 0, _MAX_SEED)
        check_int("size", self.size, 2)
        check_int(
            "obstacles",
            self.obstacles,
            0,
            self.size * self.size - 3,
            f" for a {self.size}x{self.size} grid with start, goal and agent kept free",
        )
        object.__setattr__(self, "worlds", check_names("worlds", self.worlds, WORLDS))
        object.__setattr__(
            self, "algorithms", check_names("algorithms", self.algorithms, ALGORITHMS)
        )
        _ = self.agent  # AgentConfig validates epsilon, gamma, alpha, eta and g_min
        try:
            _ = self.world  # WorldConfig validates the body, sensors, permutation and noise
        except (ValueError, TypeError) as error:
            raise type(error)(str(error).replace("num_distractors", "distractors")) from None
        if "q-learning" in self.algorithms:  # its state holds the pattern of all sensors
            from factorq_torch.tables import check_table_size

            world = self.world
            check_table_size(
                "q-learning",
                f"a Q-table of {world.num_cells} cells x {world.num_headings} headings x "
                f"2**{world.num_sensors} sensor patterns x {world.num_actuators} actions",
                (world.num_cells * world.num_headings << world.num_sensors) * world.num_actuators,
            )
        if self.threads is not None:
            check_int("threads", self.threads, 1)
        if self.backend not in BACKENDS:
            raise ValueError(f"backend={self.backend!r} is unknown: choose one of {BACKENDS}")
        try:
            device = torch.device(self.device)
        except (RuntimeError, TypeError):
            raise ValueError(
                f"device={self.device!r} is not a torch device (e.g. cpu, cuda, cuda:1)"
            ) from None
        if self.backend == "fast" and device.type != "cpu":
            raise ValueError(f"device={self.device!r} is not supported by backend 'fast' (cpu)")
        if not isinstance(self.out, str | os.PathLike) or not str(self.out):
            raise ValueError(f"out={self.out!r} must be a directory path")
        object.__setattr__(self, "out", str(self.out))
        if Path(self.out).exists() and not Path(self.out).is_dir():
            raise ValueError(f"out={self.out!r} is an existing file: give a directory")
        if "static" in self.worlds:
            try:
                static_layout(self.world)
            except ValueError as error:
                raise ValueError(str(error).replace("num_obstacles", "obstacles")) from None

    @property
    def agent(self) -> AgentConfig:
        """The learning parameters, validated."""
        return AgentConfig(
            epsilon=self.epsilon, gamma=self.gamma, alpha=self.alpha, eta=self.eta, g_min=self.g_min
        )

    @property
    def world(self) -> WorldConfig:
        """The world of every experiment; the obstacle period is set per experiment."""
        return WorldConfig(
            size=self.size,
            num_obstacles=self.obstacles,
            obstacle_period=0,
            max_steps=self.max_steps,
            layout_seed=self.layout_seed,
            body=self.body,
            sensors=self.sensors,
            num_distractors=self.distractors,
            sensor_permutation=self.sensor_permutation,
            sensor_noise=self.sensor_noise,
            actuator_noise=self.actuator_noise,
        )

    @property
    def cells(self) -> list[tuple[str, str]]:
        """The selected ``(world, algorithm)`` cells, in canonical order."""
        return [(world, algorithm) for world in self.worlds for algorithm in self.algorithms]


def field_docs(cls: type) -> dict[str, str]:
    """The one-line docstrings written under the fields of dataclass ``cls`` (for --help)."""
    try:
        tree = ast.parse(inspect.getsource(cls))
    except (OSError, TypeError):
        return {}
    docs = {}
    body = tree.body[0].body
    for node, following in zip(body, body[1:], strict=False):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docs[node.target.id] = " ".join(following.value.value.split())
    return docs


# --------------------------------------------------------------------------------------------
# Running the experiments


class Progress(NamedTuple):
    """What ``run`` reports to its ``progress`` callback after every chunk of work."""

    episodes_completed: int
    episodes_total: int
    experiments_finished: int
    experiments_total: int


ProgressCallback = Callable[[Progress], None]


def resolve_backend(config: PaperConfig) -> str:
    """The backend ``run`` will use: ``"fast"`` or ``"modular"``.

    This is the one place where the backend is chosen. ``auto`` takes the compiled fast path when
    it is available on this machine and the device is the cpu, the modular torchrl path otherwise.
    """
    from trainers import fast

    on_cpu = torch.device(config.device).type == "cpu"
    if config.backend == "fast" and not fast.is_available():
        raise ValueError(f"backend='fast' is unavailable here: {fast.unavailable_reason()}")
    unsupported = fast.unsupported_reason(config.world)
    if config.backend == "fast" and unsupported is not None:
        raise ValueError(f"backend='fast' cannot run this config: {unsupported}")
    if config.backend == "auto":
        usable = on_cpu and fast.is_available() and unsupported is None
        return "fast" if usable else "modular"
    return config.backend


def experiment_keys(
    config: PaperConfig, algorithm: str
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Obstacle periods, world keys and policy keys ``[W * S]`` of one algorithm's experiments.

    Experiments are ordered world-major (``config.worlds``), seed-minor. The key of seed index
    ``i`` in world ``w`` (index in ``WORLDS``) does not depend on what else is selected.
    """
    seeds = config.seeds
    world_index = torch.tensor([WORLDS.index(world) for world in config.worlds])  # [W]
    algorithm_index = ALGORITHMS.index(algorithm)
    world_keys = derive_keys(config.seed, STREAM_WORLD, seeds * len(WORLDS))
    world_keys = world_keys.view(seeds, len(WORLDS))  # [S, 3]: offset 3 i + w
    policy_keys = derive_keys(config.seed, STREAM_POLICY, seeds * len(WORLDS) * len(ALGORITHMS))
    policy_keys = policy_keys.view(seeds, len(WORLDS), len(ALGORITHMS))  # offset 2 (3 i + w) + a
    periods = torch.tensor([WORLD_PERIODS[world] for world in config.worlds])
    return (
        periods.repeat_interleave(seeds),  # [W * S]
        world_keys[:, world_index].T.reshape(-1),
        policy_keys[:, world_index, algorithm_index].T.reshape(-1),
    )


def _run_fast(
    config: PaperConfig,
    algorithm: str,
    periods: torch.Tensor,
    world_keys: torch.Tensor,
    policy_keys: torch.Tensor,
    report: Callable[[int, int], None],
    checkpoints: checkpoint.Checkpointer,
) -> dict[str, torch.Tensor]:
    """One algorithm's experiments on the compiled fast path, in chunks (progress, Ctrl-C,
    checkpoints)."""
    from trainers.fast import ExperimentBatch

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
    checkpoints.restore(algorithm, batch.load_state_dict)
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


def _run_modular(
    config: PaperConfig,
    algorithm: str,
    periods: torch.Tensor,
    world_keys: torch.Tensor,
    policy_keys: torch.Tensor,
    report: Callable[[int, int], None],
    checkpoints: checkpoint.Checkpointer,
) -> dict[str, torch.Tensor]:
    """One algorithm's experiments on the modular torchrl path (env, tables, policy, loss,
    ``OnlineCollector``): the fallback where no C compiler is available, and the reference the
    fast path is tested against. Same keys, so the same numbers as ``_run_fast``."""
    from tensordict.nn import TensorDictSequential
    from torchrl.envs import TransformedEnv

    from envs import FactoredGridEnv, SplitLocalReward
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.objectives import FactorQLoss, TabularQLoss
    from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
    from factorq_torch.tables import LocalRewardTable, TaskQTable

    world, agent, device = config.world, config.agent, torch.device(config.device)
    num = len(periods)
    env = grid = FactoredGridEnv(
        size=world.size,
        num_obstacles=world.num_obstacles,
        obstacle_period=periods,
        max_steps=world.max_steps,
        layout_seed=world.layout_seed,
        batch_size=(num,),
        device=device,
        body=world.body,
        sensors=world.sensors,
        num_distractors=world.num_distractors,
        sensor_permutation=world.sensor_permutation,
        sensor_noise=world.sensor_noise,
        actuator_noise=world.actuator_noise,
    )
    env.world_keys = world_keys.to(device)
    factorq = algorithm == "factor-q"
    task = TaskQTable(
        num,
        world.num_cells,
        with_sensors=not factorq,
        num_sensors=world.num_sensors,
        num_headings=world.num_headings,
        num_actions=world.num_actuators,
        device=device,
    )
    if factorq:  # the oracle: the local tables are given the body's true dependency
        local = LocalRewardTable(num, dependency=grid.dependency, device=device)
        chooser = FactorQPolicy(
            num,
            keys=policy_keys,
            epsilon=agent.epsilon,
            eta=agent.eta,
            g_min=agent.g_min,
            device=device,
        )
        policy = TensorDictSequential(task, local, chooser)
        loss = FactorQLoss(
            task, local, gamma=agent.gamma, alpha=agent.alpha, eta=agent.eta, g_min=agent.g_min
        )
        env = TransformedEnv(env, SplitLocalReward())
    else:
        chooser = EpsilonGreedyPolicy(num, keys=policy_keys, epsilon=agent.epsilon, device=device)
        policy = TensorDictSequential(task, chooser)
        loss = TabularQLoss(task, gamma=agent.gamma, alpha=agent.alpha)
    collector = OnlineCollector(
        env, policy, loss, runs=config.runs, episodes=config.episodes, progress=report
    )

    def load_state(state: dict[str, Any]) -> None:
        collector.load_state_dict(_to_device(state["collector"], device))
        saved = state["world_state"]
        for name, tensor in grid.world_state._asdict().items():
            if saved[name].shape != tensor.shape or saved[name].dtype != tensor.dtype:
                raise ValueError(f"world_state[{name!r}] does not fit this batch")
        grid.world_state = type(grid.world_state)(**_to_device(saved, device))

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
                checkpoints.save(algorithm, _to_device(state, torch.device("cpu")))
    finally:
        torch.set_num_threads(previous_threads)
    return dict(collector.metrics.items())


def _to_device(tree: Any, device: torch.device) -> Any:
    """``tree`` (nested dicts and lists of tensors) with every tensor on ``device``."""
    if isinstance(tree, torch.Tensor):
        return tree.to(device)
    if isinstance(tree, dict):
        return type(tree)((key, _to_device(value, device)) for key, value in tree.items())
    if isinstance(tree, list):
        return [_to_device(value, device) for value in tree]
    return tree


def backend_driver(backend: str) -> Callable[..., dict[str, torch.Tensor]]:
    """The function that runs one algorithm's experiments on ``backend``.

    Its signature: ``(config, algorithm, periods, world_keys, policy_keys, report, checkpoints)
    -> metrics``, where ``report(episodes_completed, experiments_finished)`` counts progress since
    its last call, ``checkpoints`` (a ``checkpoint.Checkpointer``) restores a resumed state and
    saves when due, and ``metrics`` are ``ExperimentBatch.metrics()`` (``[W * S, runs,
    episodes]`` each).
    """
    return _run_fast if backend == "fast" else _run_modular


def run(
    config: PaperConfig,
    progress: ProgressCallback | None = None,
    *,
    checkpoint_every: checkpoint.Every | str | int | None = None,
    resume: checkpoint.Checkpoint | None = None,
) -> dict[str, Any]:
    """Run the paper's experiment and return its results (the schema of ``results.json``).

    ``progress`` is called with a ``Progress`` after every chunk of work. Everything but the
    ``"timing"`` section is a function of ``config`` alone (same config, same numbers), however
    often the run was interrupted and resumed.

    ``checkpoint_every`` (episodes summed over all experiments, or seconds: ``"30s"``) saves the
    whole state to ``<config.out>/checkpoint/`` that often (see ``trainers.checkpoint``); the
    caller removes it with ``checkpoint.remove(config.out)`` once the results are written.
    ``resume`` (``checkpoint.load(out)``, with ``config`` from ``resume_config``) continues from
    a checkpoint, saving at its interval unless ``checkpoint_every`` is given. A new run refuses
    an ``out`` that holds an unfinished run's checkpoint.
    """
    started = time.perf_counter()
    backend = resolve_backend(config)
    driver = backend_driver(backend)
    if backend == "modular" and config.backend == "auto":
        from trainers import fast

        unsupported = fast.unsupported_reason(config.world)
        if unsupported is not None:  # the one-line notice of a fall-back (issue 11)
            print(
                f"factorq: the fast path cannot run this config ({unsupported}): running on "
                f"the modular torchrl path",
                file=sys.stderr,
            )
    if resume is not None:
        _check_same_config(resume.config, config_dict(config), f"resume='{resume.path.parents[1]}'")
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

    def advance_progress(episodes: int, experiments: int) -> None:
        checkpoints.advance(episodes, experiments)
        report_progress()

    report_progress()
    metrics: dict[tuple[str, str], dict[str, np.ndarray]] = {}
    for algorithm in config.algorithms:
        periods, world_keys, policy_keys = experiment_keys(config, algorithm)
        batch = checkpoints.finished.get(algorithm)
        if batch is None:
            batch = driver(
                config, algorithm, periods, world_keys, policy_keys, advance_progress, checkpoints
            )
            checkpoints.finish(algorithm, batch)
        for position, world in enumerate(config.worlds):
            rows = slice(position * config.seeds, (position + 1) * config.seeds)
            metrics[world, algorithm] = {
                name: batch[name][rows].cpu().numpy() for name in (*CURVES, "task_return")
            }
    results = summarise(config, metrics)
    wall = checkpoints.elapsed_s
    env_steps = int(sum(cell["steps"].sum() for cell in metrics.values()))
    results["timing"] = {
        "wall_s": round(wall, 3),
        "backend": backend,
        "threads": config.threads if config.threads is not None else torch.get_num_threads(),
        "env_steps": env_steps,
        "env_steps_per_s": round(env_steps / max(wall, 1e-9)),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    if checkpoint_every is not None or resume is not None:
        results["timing"]["checkpoints"] = {
            "every": None if checkpoints.every is None else str(checkpoints.every),
            "saved": checkpoints.saves,
            "save_s": round(checkpoints.save_seconds, 3),
            "resumed_at_episode": None if resume is None else resume.episodes_completed,
            "this_process_s": round(time.perf_counter() - started, 3),
        }
    return results


#: Config fields a resumed run may change: they do not change the numbers.
RESUMABLE_CHANGES = ("out", "threads")


def resume_config(
    saved: dict[str, Any], given: dict[str, Any], directory: str | os.PathLike
) -> PaperConfig:
    """The config to resume the run of ``directory`` with: the checkpoint's ``saved`` config
    dict, with the ``given`` options (field -> value) that may change (``RESUMABLE_CHANGES``).

    Any other given option must equal the saved value (a ValueError names each that differs);
    ``out`` must be ``directory`` (the saved spelling is kept when it names the same directory,
    so the results repeat it).
    """
    out = saved.get("out", "")
    if not out or Path(out).resolve() != Path(directory).resolve():
        out = str(directory)
    if "out" in given and Path(given["out"]).resolve() != Path(directory).resolve():
        raise ValueError(
            f"out='{given['out']}' differs from the resumed directory '{directory}': a resumed "
            f"run writes where its checkpoint is (leave --out out)"
        )
    try:
        checkpointed = config_from_dict({**saved, "out": out})
    except (ValueError, TypeError) as error:
        raise checkpoint.CheckpointError(
            f"resume='{directory}': the checkpoint's config is unusable here ({error})"
        ) from None
    merged = config_from_dict({**config_dict(checkpointed), **given, "out": out})
    _check_same_config(saved, config_dict(merged), f"resume='{directory}'")
    return merged


def _check_same_config(saved: dict[str, Any], config: dict[str, Any], what: str) -> None:
    differing = [
        f"{name}={_show(value)} given, {_show(saved.get(name))} in the checkpoint"
        for name, value in config.items()
        if name not in RESUMABLE_CHANGES and saved.get(name) != value
    ]
    if differing:
        raise ValueError(
            f"{what} has a checkpoint of a different config: {'; '.join(differing)} (leave "
            f"these options out to resume it, or start a new run with another --out)"
        )


def _show(value: Any) -> str:
    return ",".join(value) if isinstance(value, list | tuple) else repr(value)


# --------------------------------------------------------------------------------------------
# Statistics


def t_critical(df: int, confidence: float = CONFIDENCE) -> float:
    """The two-sided Student's t critical value: ``P(|T| <= t) = confidence`` with ``df`` dof.

    Exact for integer ``df`` (Abramowitz & Stegun 26.7.3-4, a finite series), solved by bisection.

    >>> round(t_critical(1), 3), round(t_critical(9), 3), round(t_critical(99), 3)
    (12.706, 2.262, 1.984)
    """
    if df < 1:
        raise ValueError(f"df={df} must be >= 1")
    if df > 2000:  # Cornish-Fisher expansion around the normal quantile, error < 1e-12 here
        z = 1.959963984540054 if confidence == CONFIDENCE else _normal_quantile(confidence)
        return (
            z
            + (z**3 + z) / (4 * df)
            + (5 * z**5 + 16 * z**3 + 3 * z) / (96 * df**2)
            + (3 * z**7 + 19 * z**5 + 17 * z**3 - 15 * z) / (384 * df**3)
        )

    def central_probability(t: float) -> float:
        theta = math.atan(t / math.sqrt(df))
        cos2 = math.cos(theta) ** 2
        if df % 2 == 1:
            total, term = 0.0, math.cos(theta)
            for k in range(1, (df - 1) // 2 + 1):
                total += term
                term *= cos2 * (2 * k) / (2 * k + 1)
            return 2 / math.pi * (theta + math.sin(theta) * total)
        total, term = 0.0, 1.0
        for k in range(1, df // 2 + 1):
            total += term
            term *= cos2 * (2 * k - 1) / (2 * k)
        return math.sin(theta) * total

    low, high = 0.0, 1e6
    for _ in range(200):
        middle = (low + high) / 2
        if central_probability(middle) < confidence:
            low = middle
        else:
            high = middle
    return (low + high) / 2


def _normal_quantile(confidence: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(0.5 + confidence / 2)


def mean_ci(samples: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Mean over axis 0 and its Student-t 95% interval (``None`` with fewer than 2 samples)."""
    samples = np.asarray(samples, dtype=np.float64)
    mean = samples.mean(axis=0)
    count = samples.shape[0]
    if count < 2:
        return mean, None, None
    half = t_critical(count - 1) * samples.std(axis=0, ddof=1) / math.sqrt(count)
    return mean, mean - half, mean + half


def _bootstrap_indices(seed: int, count: int) -> np.ndarray:
    """``[BOOTSTRAP_RESAMPLES, count]`` resampled seed indices, reproducible from ``seed``."""
    generator = np.random.Generator(np.random.PCG64([seed, 0xB007]))
    return generator.integers(0, count, size=(BOOTSTRAP_RESAMPLES, count))


def _quantiles(values: np.ndarray) -> list[float | None]:
    """The 2.5% and 97.5% order statistics of the bootstrap values (inf kept, NaN -> None)."""
    tail = (1 - CONFIDENCE) / 2
    bounds = np.quantile(values, [tail, 1 - tail], method="inverted_cdf")
    return [_finite_or_none(bound) for bound in bounds]


def _finite_or_none(value: Any) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


# --------------------------------------------------------------------------------------------
# Summaries


def summarise(
    config: PaperConfig, metrics: dict[tuple[str, str], dict[str, np.ndarray]]
) -> dict[str, Any]:
    """Results from raw metrics ``{(world, algorithm): {name: [S, runs, episodes]}}``."""
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
            summary[name] = {"mean": float(mean), "ci95": _interval(low, high)}
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
    return {
        "config": config_dict(config),
        "cells": cells,
        "claims": compute_claims(cells, config.seed),
        "statistics": {
            "confidence": CONFIDENCE,
            "means": "Student's t interval across seeds",
            "claims": f"percentile bootstrap over seeds, paired across cells, "
            f"{BOOTSTRAP_RESAMPLES} resamples, generator PCG64([seed, 0xB007])",
        },
        "software": software_versions(),
    }


def _interval(low: Any, high: Any) -> list[float | None] | None:
    return None if low is None else [_finite_or_none(low), _finite_or_none(high)]


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


def software_versions() -> dict[str, str]:
    """Versions of python, the libraries that computed the results, and the platform."""
    versions = {"python": platform.python_version()}
    for package in (
        "factorq-torch",
        "torch",
        "torchrl",
        "tensordict",
        "gymnasium",
        "numpy",
        "matplotlib",
    ):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    versions["platform"] = platform.platform()
    return versions


# --------------------------------------------------------------------------------------------
# Claims (SPEC section 5)

CLAIM_STATEMENTS = {
    "C1": "Factor-Q beats Q-learning on every measure, in every world",
    "C2": "in the static world learning speed is not significantly different",
    "C3": "static-world collision avoidance is dramatically better",
    "C4": "Factor-Q learns dynamic worlds nearly as fast as the static one; "
    "Q-learning falls to about 57% in the worst case",
    "C5": "greedy collisions improved by over two orders of magnitude",
}
CLAIM_THRESHOLDS = {
    "C1": "Factor-Q / Q-learning <= 1 for all 3 measures in all 3 worlds",
    "C2": "Q-learning / Factor-Q total steps in [0.8, 1.25]",
    "C3": "Q-learning / Factor-Q collisions > 10",
    "C4": "Factor-Q moving/static speed >= 0.85 in both moving worlds; "
    "Q-learning worst in [0.45, 0.70]",
    "C5": "Q-learning / Factor-Q greedy collisions > 100 in every world",
}
MOVING = ("semi-dynamic", "dynamic")


class _Means:
    """Means per (world, algorithm, measure): point estimates, or bootstrap resamples ``[B]``."""

    def __init__(self, cells: dict[str, Any], indices: np.ndarray | None) -> None:
        self.cells = cells
        self.indices = indices

    def __call__(self, world: str, algorithm: str, measure: str) -> Any:
        values = np.asarray(self.cells[f"{world}/{algorithm}"]["per_seed"][measure], np.float64)
        if self.indices is None:
            return values.mean()
        return values[self.indices].mean(axis=1)  # [B]


def _ratio(numerator: Any, denominator: Any) -> Any:
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.divide(numerator, denominator)


def _c1(means: _Means) -> dict[str, Any]:
    measures = {}
    for world in WORLDS:
        for measure in MEASURES:
            factor_q = means(world, "factor-q", measure)
            q_learning = means(world, "q-learning", measure)
            measures[f"{world} {MEASURE_LABELS[measure]}, Factor-Q / Q-learning"] = (
                _ratio(factor_q, q_learning),
                factor_q <= q_learning,
            )
    return measures


def _c2(means: _Means) -> dict[str, Any]:
    ratio = _ratio(
        means("static", "q-learning", "total_steps"), means("static", "factor-q", "total_steps")
    )
    return {"static total steps, Q-learning / Factor-Q": (ratio, (ratio >= 0.8) & (ratio <= 1.25))}


def _c3(means: _Means) -> dict[str, Any]:
    ratio = _ratio(
        means("static", "q-learning", "collisions"), means("static", "factor-q", "collisions")
    )
    return {"static collisions, Q-learning / Factor-Q": (ratio, ratio > 10)}


def _c4(means: _Means) -> dict[str, Any]:
    measures = {}
    for algorithm in ALGORITHMS:
        static = means("static", algorithm, "total_steps")
        for world in MOVING:
            # speed = 1 / mean total steps, so moving/static speed = static steps / moving steps
            ratio = _ratio(static, means(world, algorithm, "total_steps"))
            label = f"{ALGORITHM_LABELS[algorithm]} speed, {world} / static"
            passed = ratio >= 0.85 if algorithm == "factor-q" else None
            measures[label] = (ratio, passed)
    return measures


def _c5(means: _Means) -> dict[str, Any]:
    measures = {}
    for world in WORLDS:
        ratio = _ratio(
            means(world, "q-learning", "greedy_collisions"),
            means(world, "factor-q", "greedy_collisions"),
        )
        measures[f"{world} greedy collisions, Q-learning / Factor-Q"] = (ratio, ratio > 100)
    return measures


def _worst(measures: dict[str, Any], pick: Callable, keys: list[str] | None = None) -> Any:
    values = [measures[key][0] for key in (keys or list(measures))]
    return pick(np.stack(np.broadcast_arrays(*values)), axis=0)


def _headline(claim: str, measures: dict[str, Any]) -> tuple[Any, Any]:
    """The claim's headline statistic (from its measures) and whether it passes."""
    if claim == "C1":
        return _worst(measures, np.max), np.all(np.stack([m[1] for m in measures.values()]), 0)
    if claim in ("C2", "C3"):
        (value, passed), *_ = measures.values()
        return value, passed
    if claim == "C4":
        factor_q = _worst(measures, np.min, [key for key in measures if "Factor-Q" in key])
        q_learning = _worst(measures, np.min, [key for key in measures if "Q-learning" in key])
        passed = (factor_q >= 0.85) & (q_learning >= 0.45) & (q_learning <= 0.70)
        return {"factor-q": factor_q, "q-learning": q_learning}, passed
    return _worst(measures, np.min), np.all(np.stack([m[1] for m in measures.values()]), 0)


_CLAIM_MEASURES = {"C1": _c1, "C2": _c2, "C3": _c3, "C4": _c4, "C5": _c5}
_CLAIM_CELLS = {
    "C1": [(world, algorithm) for world in WORLDS for algorithm in ALGORITHMS],
    "C2": [("static", algorithm) for algorithm in ALGORITHMS],
    "C3": [("static", algorithm) for algorithm in ALGORITHMS],
    "C4": [(world, algorithm) for world in WORLDS for algorithm in ALGORITHMS],
    "C5": [(world, algorithm) for world in WORLDS for algorithm in ALGORITHMS],
}


def compute_claims(cells: dict[str, Any], seed: int = 0) -> dict[str, Any]:
    """Claims C1-C5 of SPEC section 5 from ``cells`` (only their ``per_seed`` lists are read).

    Each claim: ``statement``, ``threshold``, ``value`` (its statistic; C4 has one per algorithm),
    ``ci95`` (bootstrap interval of ``value``, ``None`` with one seed), ``pass`` (``None`` when a
    cell it needs was not run), ``detail`` and ``measures`` (the comparisons it is made of).
    """
    seeds = {len(cell["per_seed"]["total_steps"]) for cell in cells.values()}
    if len(seeds) > 1:
        raise ValueError(f"cells have different numbers of seeds: {sorted(seeds)}")
    count = seeds.pop() if seeds else 0
    indices = _bootstrap_indices(seed, count) if count >= 2 else None
    claims = {}
    for claim, measure_fn in _CLAIM_MEASURES.items():
        entry = {
            "statement": CLAIM_STATEMENTS[claim],
            "threshold": CLAIM_THRESHOLDS[claim],
            "value": None,
            "ci95": None,
            "pass": None,
            "detail": "",
            "measures": [],
        }
        claims[claim] = entry
        missing = [f"{w}/{a}" for w, a in _CLAIM_CELLS[claim] if f"{w}/{a}" not in cells]
        if missing:
            entry["detail"] = f"not evaluated: needs {', '.join(missing)}, which were not run"
            continue
        point = measure_fn(_Means(cells, None))
        value, passed = _headline(claim, point)
        boot_value = None
        if indices is not None:
            boot = measure_fn(_Means(cells, indices))
            boot_value, _ = _headline(claim, boot)
        for name, (measure_value, measure_pass) in point.items():
            entry["measures"].append(
                {
                    "name": name,
                    "value": _finite_or_none(measure_value),
                    "ci95": None if indices is None else _quantiles(boot[name][0]),
                    "pass": None if measure_pass is None else bool(measure_pass),
                }
            )
        if isinstance(value, dict):
            entry["value"] = {key: _finite_or_none(item) for key, item in value.items()}
            if boot_value is not None:
                entry["ci95"] = {key: _quantiles(item) for key, item in boot_value.items()}
        else:
            entry["value"] = _finite_or_none(value)
            entry["ci95"] = None if boot_value is None else _quantiles(boot_value)
        entry["pass"] = bool(passed)
        entry["detail"] = _detail(claim, entry, value)
    return claims


def _detail(claim: str, entry: dict[str, Any], value: Any) -> str:
    """One sentence: what was compared, the outcome, and why."""
    measures = {measure["name"]: measure for measure in entry["measures"]}
    undefined = [name for name, measure in measures.items() if measure["value"] is None]
    note = (
        f"; undefined (0 in a denominator, reported as null): {', '.join(undefined)}"
        if undefined
        else ""
    )
    if claim == "C1":
        failing = [name for name, measure in measures.items() if not measure["pass"]]
        if failing:
            return "Factor-Q > Q-learning on: " + "; ".join(failing) + note
        closest = max(measures, key=lambda name: _sortable(measures[name]["value"]))
        return (
            f"Factor-Q <= Q-learning in all {len(measures)} comparisons; closest: {closest} = "
            f"{format_number(value)}{note}"
        )
    if claim == "C2":
        inside = "inside" if entry["pass"] else "outside"
        ratio = format_number(value)
        return f"static total steps, Q-learning / Factor-Q = {ratio}, {inside} [0.8, 1.25]{note}"
    if claim == "C3":
        return (
            f"static collisions, Q-learning / Factor-Q = {format_number(value)} "
            f"({'>' if entry['pass'] else 'not >'} 10){note}"
        )
    if claim == "C4":
        factor_q, q_learning = value["factor-q"], value["q-learning"]
        return (
            f"Factor-Q worst moving/static speed {format_number(factor_q)} "
            f"({'>=' if factor_q >= 0.85 else 'below'} 0.85); Q-learning worst "
            f"{format_number(q_learning)} ({'in' if 0.45 <= q_learning <= 0.70 else 'outside'} "
            f"[0.45, 0.70]){note}"
        )
    smallest = min(measures, key=lambda name: _sortable(measures[name]["value"]))
    failing = [name.split(" ")[0] for name, measure in measures.items() if not measure["pass"]]
    outcome = f"not > 100 in: {', '.join(failing)}" if failing else "> 100 in every world"
    return f"smallest ratio {format_number(value)} ({smallest.split(' ')[0]}); {outcome}{note}"


def _sortable(value: float | None) -> float:
    return math.inf if value is None else value


def format_number(value: float | None) -> str:
    """A number for people: 3 significant digits, thousands unseparated, ``inf``/``n/a``."""
    if value is None:
        return "n/a"
    value = float(value)
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    if math.isnan(value):
        return "n/a"
    if value == 0:
        return "0"
    magnitude = math.floor(math.log10(abs(value)))
    if magnitude >= 3:
        return f"{value:.0f}"
    return f"{value:.{max(2 - magnitude, 0)}f}"


# --------------------------------------------------------------------------------------------
# Writing results


def dumps_results(results: dict[str, Any]) -> str:
    """``results`` as JSON: indented, lists of numbers on one line, non-finite numbers as null."""
    return _dumps(results, 0) + "\n"


def _dumps(value: Any, level: int) -> str:
    if isinstance(value, float | np.floating):
        return json.dumps(_finite_or_none(value))
    if isinstance(value, dict):
        if not value:
            return "{}"
        inner = "  " * (level + 1)
        items = [f"{inner}{json.dumps(str(k))}: {_dumps(v, level + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + "  " * level + "}"
    if isinstance(value, list | tuple):
        if all(not isinstance(item, dict | list | tuple) for item in value):
            return "[" + ", ".join(_dumps(item, level) for item in value) + "]"
        inner = "  " * (level + 1)
        items = [f"{inner}{_dumps(item, level + 1)}" for item in value]
        return "[\n" + ",\n".join(items) + "\n" + "  " * level + "]"
    if isinstance(value, np.integer | np.bool_):
        return json.dumps(value.item())
    return json.dumps(value)


def write_atomic(path: str | os.PathLike, write: Callable[[Path], None]) -> None:
    """Call ``write(temporary)`` next to ``path``, then rename it to ``path`` (all or nothing).

    A reader never sees a partial file; an interrupted write leaves the old file (if any) intact.
    """
    write_all_atomic({Path(path): write})


def write_all_atomic(writers: dict[Path, Callable[[Path], None]]) -> None:
    """Write every file to a temporary next to it, then rename them all into place, in order.

    The slow part (drawing, serialising) happens before any rename, so an interruption leaves
    either all the old files or, but for a few renames' time, all the new ones.
    """
    temporaries = {path: path.with_name(f".{path.name}.{os.getpid()}.tmp") for path in writers}
    try:
        for path, write in writers.items():
            write(temporaries[path])
        for path, temporary in temporaries.items():
            os.replace(temporary, path)
    finally:
        for temporary in temporaries.values():
            temporary.unlink(missing_ok=True)


def write_results(results: dict[str, Any], out_dir: str | os.PathLike) -> dict[str, Path]:
    """Write ``results.json``, ``figure3.png`` and ``report.md`` to ``out_dir``, atomically.

    ``results.json`` is renamed into place first: a results file on disk is always complete, and
    ``factorq report`` can redraw the other two from it.
    """
    from trainers import report

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "results": out / RESULTS_FILE,
        "figure": out / FIGURE_FILE,
        "report": out / REPORT_FILE,
    }
    write_all_atomic(
        {
            paths["results"]: lambda path: path.write_text(dumps_results(results)),
            paths["figure"]: lambda path: report.figure3(results, path),
            paths["report"]: lambda path: path.write_text(report.report_markdown(results)),
        }
    )
    return paths
