"""``factorq compare``: tabular Factor-Q and Q-learning, DQN and neural Factor-Q (Factor-DQN) on
the three worlds, for ``seeds`` independent experiments and a budget of ``steps`` env steps each.

    config -> for each method: one batch of (worlds x seeds) experiments -> per-episode traces
           -> steps to threshold, collisions, greedy collisions -> comparison.json / .png / .md

**Step budget.** Every experiment gets exactly ``steps`` env steps, episodes being as many as fit
(the last one may be cut by the budget: its collisions count, its path length does not). This is
not the paper's runs x episodes protocol: a budget of env steps is what makes DQN, which trains on
a replay buffer, comparable with the online methods. Tabular methods and Factor-DQN run in the
project's ``OnlineCollector`` (one run, stepped ``steps`` times), DQN in torchrl's ``Collector``
(``trainers.dqn``).

**The swap.** Factor-Q and Factor-DQN run the very same code (``run_online``): env with
``SplitLocalReward``, ``FactorQPolicy`` (eqs. 2-3), ``FactorQLoss`` (eq. 4, and eq. 5 or its
regression), ``OnlineCollector``. Only ``value_providers`` differs: tables and SGD(lr 1), or
networks (``factorq_torch.neural``) and Adam.

**Threshold.** ``steps_to_threshold`` is the env steps at the end of the first episode whose path
length is within 1.5x the shortest path: the BFS distance from start to goal in the static layout;
in the moving worlds, where the shortest path changes with every scatter, the obstacle-free
Manhattan distance ``2 (size - 1)``. Per method and world it is the mean over seeds when every
seed reached it, ``null`` otherwise (``seeds_reached`` says how many did).

**Wall time.** Each method runs all selected worlds and seeds as one batch, so ``wall_s`` is that
batch's time, the same for each of its worlds.

**Logging.** torchrl's ``CSVLogger`` (default) or ``TensorboardLogger`` (``logger="tensorboard"``)
under ``out/logs/<method>/``: per experiment and finished episode, ``return`` (task return),
``path_length``, ``collisions``, ``greedy_collisions``, ``epsilon`` and ``loss`` (0.5 x squared TD
error: of each step's update for the online methods, of the latest minibatch for DQN; averaged
over the episode's steps), at step = that experiment's env steps.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import sys
import time
import typing
from collections import deque
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv

from envs.transforms import SplitLocalReward
from envs.world import START_CELL, static_layout
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_LOCAL_NETWORK, STREAM_POLICY, STREAM_TASK_NETWORK
from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_torch.collectors import OnlineCollector
from factorq_torch.neural import (
    ACTIVATIONS,
    LocalRewardNetwork,
    TaskQNetwork,
)
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable
from trainers import dqn
from trainers.cli import COMPARE_HELP
from trainers.dqn import (
    METHODS,
    WORLDS,
    DQNConfig,
    EpisodeRecorder,
    ExperimentConfig,
    check_hidden,
    experiment_keys,
    make_env,
)
from trainers.paper import field_docs, mean_ci

LOGGERS = ("csv", "tensorboard")
THRESHOLD_FACTOR = 1.5
JSON_FILE = "comparison.json"
FIGURE_FILE = "comparison.png"
REPORT_FILE = "comparison.md"
CURVE_POINTS = 100
METHOD_LABELS = {
    "factor-q": "Factor-Q (tabular)",
    "q-learning": "Q-learning (tabular)",
    "dqn": "DQN",
    "factor-dqn": "Factor-DQN (neural Factor-Q)",
}
COLOURS = {
    "factor-q": "#0072B2",
    "q-learning": "#D55E00",
    "dqn": "#009E73",
    "factor-dqn": "#CC79A7",
}
_MAX_SEED = 2**63 - 1


@dataclass(frozen=True)
class FactorDQNConfig:
    """Neural Factor-Q's networks, optimiser and exploration (eqs. 2-4 use ``AgentConfig``'s
    gamma, alpha, eta and g_min; the local network's defaults are explained in
    ``factorq_torch.neural``).

    ``epsilon`` is 0.05, not the paper's 0.01: with 0.01, about one experiment in nine (measured
    on the default comparison) had its task network settle on the value of never arriving,
    ``-1 / (1 - gamma) = -10`` in every cell, and loop between two cells for 1,000-3,000 steps.
    The hidden layer spreads every update to cells not yet visited, so the optimistic zero start
    that makes tabular Factor-Q explore is soon gone, and 0.01 rarely breaks such a loop. 0.05 did
    in every run measured, at the price of more exploratory collisions (greedy ones unchanged).
    """

    hidden: tuple[int, ...] = (64,)
    """Hidden layer widths of each experiment's task Q-network (input: the cell one-hot)."""
    activation: str = "relu"
    """Hidden activation of the task Q-network: tanh or relu."""
    local_hidden: tuple[int, ...] = (8,)
    """Hidden layer widths of each actuator's local reward network (input: its sensor bit)."""
    local_bias: bool = False
    """Biases in the local networks (False: nothing sensed predicts exactly 0; see neural.py)."""
    lr: float = 1e-3
    """Adam learning rate of the task Q-network."""
    local_lr: float = 1e-2
    """Adam learning rate of the local reward networks."""
    local_activation: str = "tanh"
    """Hidden activation of the local networks: tanh or relu."""
    local_shared: bool = True
    """One local network per experiment shared by its four actuators (else one per actuator)."""
    epsilon: float = 0.05
    """Exploration probability of FactorQPolicy (tabular Factor-Q: the paper's 0.01)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "hidden", check_hidden("hidden", self.hidden))
        object.__setattr__(self, "local_hidden", check_hidden("local_hidden", self.local_hidden))
        for name in ("local_bias", "local_shared"):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"{name} must be a bool, got {getattr(self, name)!r}")
        for name in ("activation", "local_activation"):
            if getattr(self, name) not in ACTIVATIONS:
                raise ValueError(
                    f"{name}={getattr(self, name)!r} is unknown: choose one of "
                    f"{', '.join(ACTIVATIONS)}"
                )
        check_float("lr", self.lr, 0.0, 1.0, low_open=True)
        check_float("local_lr", self.local_lr, 0.0, 1.0, low_open=True)
        check_float("epsilon", self.epsilon, 0.0, 1.0)


@dataclass(frozen=True)
class CompareConfig:
    """The comparison: methods x worlds, ``seeds`` experiments each, ``steps`` env steps each."""

    seed: int = 0
    """Master seed: worlds, policies and network initialisations derive from it."""
    seeds: int = 3
    """Independent experiments per method and world; 95% intervals are across them."""
    steps: int = 15_000
    """Budget of env steps per experiment."""
    worlds: tuple[str, ...] = WORLDS
    """Worlds to run: static, semi-dynamic, dynamic (comma-separated)."""
    methods: tuple[str, ...] = METHODS
    """Methods to run: factor-q, q-learning, dqn, factor-dqn (comma-separated)."""
    out: str = "results/compare"
    """Directory for comparison.json, comparison.png, comparison.md and logs/."""
    logger: str = "csv"
    """Per-episode logs: csv (torchrl CSVLogger) or tensorboard (needs the tensorboard package)."""
    size: int = 10
    """Side of the square grid, in cells."""
    obstacles: int = 10
    """Number of single-cell obstacles."""
    max_steps: int = 10_000
    """Actions after which an episode is truncated."""
    layout_seed: int = 0
    """Seed of the static world's obstacle layout."""
    body: str = "translate"
    """Agent body: translate (the paper) or heading (forward, turn left/right)."""
    sensors: str = "cross"
    """Sensor layout: cross (the paper: 4 neighbours) or ring (8 neighbours)."""
    distractors: int = 0
    """Extra sensor bits that carry no information."""
    sensor_permutation: int | None = None
    """Seed of a random order in which the agent receives its sensors."""
    sensor_noise: float = 0.0
    """Probability that each sensor bit is flipped at each observation, in [0, 1]."""
    actuator_noise: float = 0.0
    """Probability that another actuator fires than the chosen one, in [0, 1]."""
    threads: int = 1
    """CPU threads for torch (1 is fastest on these tiny tensors)."""
    agent: AgentConfig = AgentConfig()
    """Tabular and Factor-DQN parameters: epsilon, gamma, alpha, eta, g_min (the paper's)."""
    dqn: DQNConfig = DQNConfig()
    """DQN's hyperparameters (trainers.dqn)."""
    factor_dqn: FactorDQNConfig = FactorDQNConfig()
    """Factor-DQN's networks and learning rates."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        if self.logger not in LOGGERS:
            raise ValueError(
                f"logger={self.logger!r} is unknown: choose one of {', '.join(LOGGERS)}"
            )
        if self.logger == "tensorboard" and importlib.util.find_spec("tensorboard") is None:
            raise ValueError(
                "logger='tensorboard' needs the tensorboard package, which is not installed: "
                "`pip install tensorboard` (the extra: `pip install -e '.[tensorboard]'`), "
                "or use logger='csv'"
            )
        if not isinstance(self.out, str | os.PathLike) or not str(self.out):
            raise ValueError(f"out={self.out!r} must be a directory path")
        object.__setattr__(self, "out", str(self.out))
        check_int("threads", self.threads, 1)
        for name, kind in (
            ("agent", AgentConfig),
            ("dqn", DQNConfig),
            ("factor_dqn", FactorDQNConfig),
        ):
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        # ExperimentConfig validates seed, seeds, steps, worlds and the world, naming the option.
        object.__setattr__(self, "worlds", self.experiments.worlds)

    @property
    def experiments(self) -> ExperimentConfig:
        return ExperimentConfig(
            seed=self.seed,
            seeds=self.seeds,
            worlds=self.worlds,
            steps=self.steps,
            size=self.size,
            obstacles=self.obstacles,
            max_steps=self.max_steps,
            layout_seed=self.layout_seed,
            body=self.body,
            sensors=self.sensors,
            distractors=self.distractors,
            sensor_permutation=self.sensor_permutation,
            sensor_noise=self.sensor_noise,
            actuator_noise=self.actuator_noise,
        )


# --------------------------------------------------------------------------------------------
# The online methods: one loop, two kinds of value providers


def value_providers(
    method: str, config: CompareConfig, count: int
) -> tuple[Any, Any, torch.optim.Optimizer | None]:
    """The task and local value providers of ``method`` and their optimizer.

    The only place where tabular and neural Factor-Q differ: tables (eq. 5 applied by the loss
    through ``update_running_mean``, eq. 4 by SGD of learning rate 1, ``optimizer=None``) or
    networks (``loss_task`` and ``loss_local`` by Adam).
    """
    experiments = config.experiments
    cells = experiments.size**2
    world = experiments.world  # the body: tables and networks get its shapes and dependency
    shapes = {"num_headings": world.num_headings, "num_actions": world.num_actuators}
    if method == "q-learning":
        table = TaskQTable(count, cells, with_sensors=True, num_sensors=world.num_sensors, **shapes)
        return table, None, None
    if method == "factor-q":
        return (
            TaskQTable(count, cells, **shapes),
            LocalRewardTable(count, dependency=world.dependency),
            None,
        )
    if method == "factor-dqn":
        settings = config.factor_dqn
        task = TaskQNetwork(
            count,
            cells,
            **shapes,
            hidden=settings.hidden,
            activation=settings.activation,
            keys=experiment_keys(experiments, STREAM_TASK_NETWORK, method),
        )
        local = LocalRewardNetwork(
            count,
            dependency=world.dependency,
            hidden=settings.local_hidden,
            bias=settings.local_bias,
            activation=settings.local_activation,
            shared=settings.local_shared,
            keys=experiment_keys(experiments, STREAM_LOCAL_NETWORK, method),
        )
        optimizer = torch.optim.Adam(
            [
                {"params": task.parameters(), "lr": settings.lr},
                {"params": local.parameters(), "lr": settings.local_lr},
            ]
        )
        return task, local, optimizer
    raise ValueError(
        f"method={method!r} is not an online method (factor-q, q-learning, factor-dqn)"
    )


def run_online(method: str, config: CompareConfig, logger=None, progress=None) -> dict[str, Any]:
    """Tabular Factor-Q, tabular Q-learning or Factor-DQN for the step budget (OnlineCollector).

    Returns ``{"traces", "wall_s"}`` like ``trainers.dqn.run``.
    """
    started = time.perf_counter()
    experiments, agent = config.experiments, config.agent
    count, steps = experiments.num_experiments, experiments.steps
    env = make_env(experiments)
    task, local, optimizer = value_providers(method, config, count)
    policy_keys = experiment_keys(experiments, STREAM_POLICY, method)
    epsilon = config.factor_dqn.epsilon if method == "factor-dqn" else agent.epsilon
    if local is None:
        chooser = EpsilonGreedyPolicy(count, epsilon=epsilon, keys=policy_keys)
        policy = TensorDictSequential(task, chooser)
        loss = TabularQLoss(task, gamma=agent.gamma, alpha=agent.alpha)
    else:
        env = TransformedEnv(env, SplitLocalReward())
        chooser = FactorQPolicy(
            count, epsilon=epsilon, eta=agent.eta, g_min=agent.g_min, keys=policy_keys
        )
        policy = TensorDictSequential(task, local, chooser)
        loss = FactorQLoss(
            task, local, gamma=agent.gamma, alpha=agent.alpha, eta=agent.eta, g_min=agent.g_min
        )
    # An episode takes at least the Manhattan distance, so this many always fit the budget.
    episodes = steps // (2 * (experiments.size - 1)) + 1
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=episodes, optimizer=optimizer)
    captured: dict[str, torch.Tensor] = {}
    hook = loss.register_forward_hook(lambda module, inputs, output: captured.update(output))
    recorder = EpisodeRecorder(experiments.labels, logger)
    report_every = max(1, steps // 100)
    for step in range(1, steps + 1):
        td = collector.step()
        recorder.update(td, epsilon, 0.5 * captured["td_error"].pow(2))
        if progress is not None and (step % report_every == 0 or step == steps):
            progress(step, steps)
    hook.remove()
    return {"traces": recorder.traces(), "wall_s": time.perf_counter() - started}


# --------------------------------------------------------------------------------------------
# Summaries


def shortest_path_length(experiments: ExperimentConfig, world: str) -> int:
    """BFS distance start -> goal in the static layout; ``2 (size - 1)`` in a moving world."""
    size = experiments.size
    if world != "static":
        return 2 * (size - 1)
    blocked = static_layout(experiments.world).tolist()  # [N] bool
    goal = size * size - 1
    distance = {START_CELL: 0}
    queue = deque([START_CELL])
    while queue:
        cell = queue.popleft()
        if cell == goal:
            return distance[cell]
        row, col = divmod(cell, size)
        for d_row, d_col in ((-1, 0), (0, -1), (1, 0), (0, 1)):
            r, c = row + d_row, col + d_col
            nxt = r * size + c
            if 0 <= r < size and 0 <= c < size and not blocked[nxt] and nxt not in distance:
                distance[nxt] = distance[cell] + 1
                queue.append(nxt)
    raise ValueError(f"the static layout (layout_seed={experiments.layout_seed}) has no path")


def steps_to_threshold(trace: dict[str, Any], threshold: float) -> int | None:
    """Env steps at the end of the first episode with path length <= ``threshold`` (or None)."""
    reached = np.flatnonzero(trace["steps"] <= threshold)
    return int(trace["env_steps"][reached[0]]) if reached.size else None


def _scalar_ci(samples: list[float]) -> tuple[float, float | None, float | None]:
    """``paper.mean_ci`` of per-seed scalars, as plain floats for JSON."""
    mean, low, high = mean_ci(samples)
    return float(mean), None if low is None else float(low), None if high is None else float(high)


def _curve(traces: list[dict[str, Any]], name: str, grid: np.ndarray) -> dict[str, list]:
    """Per-episode ``name`` against env steps: for every seed, the mean over the episodes that
    ended in each interval ``(grid[k-1], grid[k]]`` (the last value carried over an interval where
    none ended, NaN before the first), then the mean and 95% band across seeds where every seed
    has a value."""
    values = np.full((len(traces), grid.size), np.nan)
    for row, trace in enumerate(traces):
        interval = np.searchsorted(grid, trace["env_steps"], side="left")  # [episodes]
        inside = interval < grid.size
        totals = np.bincount(interval[inside], trace[name][inside], minlength=grid.size)
        counts = np.bincount(interval[inside], minlength=grid.size)
        last = np.nan
        for k in range(grid.size):
            last = totals[k] / counts[k] if counts[k] else last
            values[row, k] = last
    mean = np.full(grid.size, np.nan)
    low, high = mean.copy(), mean.copy()
    complete = ~np.isnan(values).any(axis=0)
    if complete.any():
        mean[complete], band_low, band_high = mean_ci(values[:, complete])
        if band_low is not None:
            low[complete], high[complete] = band_low, band_high
    return {"mean": _json_list(mean), "low": _json_list(low), "high": _json_list(high)}


def _json_list(values: np.ndarray) -> list[float | None]:
    return [float(value) if math.isfinite(value) else None for value in values]


def summarise(config: CompareConfig, runs: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The ``comparison.json`` dict from every method's ``{"traces", "wall_s"}``."""
    experiments = config.experiments
    grid = np.linspace(experiments.steps / CURVE_POINTS, experiments.steps, CURVE_POINTS)
    thresholds = {}
    for world in experiments.worlds:
        shortest = shortest_path_length(experiments, world)
        thresholds[world] = {"shortest_path": shortest, "threshold": THRESHOLD_FACTOR * shortest}
    results: dict[str, Any] = {}
    curves: dict[str, Any] = {}
    for method, run in runs.items():
        results[method], curves[method] = {}, {}
        for world in experiments.worlds:
            traces = [trace for trace in run["traces"] if trace["world"] == world]
            reached = [steps_to_threshold(t, thresholds[world]["threshold"]) for t in traces]
            hit = [value for value in reached if value is not None]
            collisions = _scalar_ci([t["total_collisions"] for t in traces])
            greedy = _scalar_ci([t["total_greedy_collisions"] for t in traces])
            avoidable = _scalar_ci(
                [
                    t["total_greedy_collisions"] - t["total_boxed_in_greedy_collisions"]
                    for t in traces
                ]
            )
            tail = [t["steps"][t["env_steps"] > 0.8 * experiments.steps] for t in traces]
            tail = [float(values.mean()) for values in tail if values.size]
            results[method][world] = {
                "steps_to_threshold": float(np.mean(hit)) if len(hit) == len(traces) else None,
                "collisions": collisions[0],
                "greedy_collisions": greedy[0],
                "wall_s": round(float(run["wall_s"]), 3),
                "seeds_reached": len(hit),
                "steps_to_threshold_per_seed": reached,
                "collisions_ci95": [collisions[1], collisions[2]],
                "greedy_collisions_ci95": [greedy[1], greedy[2]],
                "avoidable_greedy_collisions": avoidable[0],
                "avoidable_greedy_collisions_ci95": [avoidable[1], avoidable[2]],
                "episodes": float(np.mean([t["steps"].size for t in traces])),
                "final_path_length": float(np.mean(tail)) if len(tail) == len(traces) else None,
            }
            curves[method][world] = {
                name: _curve(traces, name, grid) for name in ("steps", "collisions")
            }
    return {
        "config": config_dict(config),
        "thresholds": thresholds,
        "results": results,
        "curves": {"env_steps": [float(x) for x in grid], **curves},
    }


def config_dict(config: CompareConfig) -> dict[str, Any]:
    """``config`` as JSON-ready values (tuples as lists, nested configs as dicts)."""
    return json.loads(json.dumps(asdict(config)))


# --------------------------------------------------------------------------------------------
# Output


def write_figure(results: dict[str, Any], path: str | os.PathLike) -> None:
    """Steps and collisions per episode against env steps, mean and 95% band, one column a world."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    worlds = list(results["thresholds"])
    grid = np.asarray(results["curves"]["env_steps"])
    figure = Figure(figsize=(4.2 * len(worlds), 7.0), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(2, len(worlds), squeeze=False, sharex=True)
    rows = (("steps", "steps per episode"), ("collisions", "collisions per episode"))
    for column, world in enumerate(worlds):
        for row, (name, label) in enumerate(rows):
            axis = axes[row][column]
            for method in results["results"]:
                curve = results["curves"][method][world][name]
                mean = np.array([np.nan if v is None else v for v in curve["mean"]])
                low = np.array([np.nan if v is None else v for v in curve["low"]])
                high = np.array([np.nan if v is None else v for v in curve["high"]])
                colour = COLOURS[method]
                floor = 1.0 if name == "steps" else 0.0  # a path takes >= 1 step
                axis.plot(grid, mean, color=colour, label=METHOD_LABELS[method], linewidth=1.4)
                axis.fill_between(grid, np.maximum(low, floor), high, color=colour, alpha=0.2)
            if name == "steps":
                axis.axhline(
                    results["thresholds"][world]["threshold"],
                    color="grey",
                    linestyle=":",
                    linewidth=1.0,
                    label=f"{THRESHOLD_FACTOR}x shortest path",
                )
                axis.set_title(f"{world} world")
                axis.set_yscale("log")
            else:  # symlog: linear near 0, where the Factor-Q curves end up
                axis.set_yscale("symlog", linthresh=1.0)
                axis.set_ylim(bottom=0.0)
            axis.set_xlim(0, grid[-1])
            axis.set_ylabel(label)
            if row == len(rows) - 1:
                axis.set_xlabel("env steps per experiment")
    axes[0][0].legend(fontsize="small")
    figure.suptitle(
        f"per-episode means over each 1/{grid.size} of the budget; mean over "
        f"{results['config']['seeds']} seeds with 95% bands",
        fontsize="medium",
    )
    figure.savefig(path, dpi=110)


def _number(value: float | None, digits: int = 0) -> str:
    if value is None:
        return "never"
    return f"{value:,.{digits}f}"


def report_markdown(results: dict[str, Any]) -> str:
    """``comparison.md``: one row per method and world."""
    config = results["config"]
    lines = [
        "# factorq compare",
        "",
        f"{config['seeds']} seeds x {config['steps']:,} env steps per experiment, "
        f"{config['size']}x{config['size']} grid, {config['obstacles']} obstacles, "
        f"master seed {config['seed']}. Means over seeds (95% interval in brackets).",
        "",
        "- **steps to threshold**: env steps until the first episode whose path is within "
        f"{THRESHOLD_FACTOR}x the shortest path (static: BFS in the layout; moving worlds: the "
        "Manhattan distance); `never` unless every seed reached it (reached: seeds that did).",
        "- **collisions**, **greedy collisions** (on non-exploratory actions): totals over the "
        "budget; **avoidable**: the greedy collisions where some direction was free (not boxed in "
        "by walls and obstacles on all four sides). **final path**: mean path length of the "
        "episodes ending in the last 20% of the budget.",
        "- **wall s**: the method's batch (all worlds and seeds at once).",
        "",
        "| method | world | steps to threshold | reached | collisions | greedy collisions "
        "| avoidable | final path | wall s |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, worlds in results["results"].items():
        for world, cell in worlds.items():
            low, high = cell["collisions_ci95"]
            g_low, g_high = cell["greedy_collisions_ci95"]
            collisions = _number(cell["collisions"], 1)
            greedy = _number(cell["greedy_collisions"], 1)
            if low is not None:
                collisions += f" [{max(low, 0):,.0f}, {high:,.0f}]"
                greedy += f" [{max(g_low, 0):,.0f}, {g_high:,.0f}]"
            lines.append(
                f"| {METHOD_LABELS[method]} | {world} | {_number(cell['steps_to_threshold'])} "
                f"| {cell['seeds_reached']}/{config['seeds']} | {collisions} | {greedy} "
                f"| {_number(cell['avoidable_greedy_collisions'], 1)} "
                f"| {_number(cell['final_path_length'], 1)} | {cell['wall_s']:.0f} |"
            )
    thresholds = ", ".join(
        f"{world} {entry['shortest_path']} -> {entry['threshold']:g}"
        for world, entry in results["thresholds"].items()
    )
    lines += ["", f"Shortest path -> threshold: {thresholds}.", ""]
    return "\n".join(lines)


def write_outputs(results: dict[str, Any], out: str | os.PathLike) -> dict[str, Path]:
    """Write comparison.json, comparison.png and comparison.md to ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": out / JSON_FILE, "figure": out / FIGURE_FILE, "report": out / REPORT_FILE}
    paths["json"].write_text(json.dumps(results, indent=1, allow_nan=False) + "\n")
    write_figure(results, paths["figure"])
    paths["report"].write_text(report_markdown(results))
    return paths


# --------------------------------------------------------------------------------------------
# Running


def make_logger(config: CompareConfig, method: str):
    """torchrl's CSVLogger or TensorboardLogger for ``method`` under ``out/logs/``."""
    log_dir = str(Path(config.out) / "logs")
    if config.logger == "tensorboard":
        from torchrl.record.loggers.tensorboard import TensorboardLogger

        return TensorboardLogger(exp_name=method, log_dir=log_dir)
    from torchrl.record.loggers.csv import CSVLogger

    return CSVLogger(exp_name=method, log_dir=log_dir)


#: ``progress(method, done, total)``: env steps per experiment done so far for ``method``.
Progress = Callable[[str, int, int], None]


def run(config: CompareConfig, progress: Progress | None = None) -> dict[str, Any]:
    """Run every selected method on every selected world; return the ``comparison.json`` dict."""
    started = time.perf_counter()
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        runs = {}
        for method in config.methods:
            logger = make_logger(config, method)
            report = None if progress is None else (lambda d, t, m=method: progress(m, d, t))
            if method == "dqn":
                runs[method] = dqn.run(
                    config.dqn, config.experiments, logger=logger, progress=report
                )
            else:
                runs[method] = run_online(method, config, logger=logger, progress=report)
    finally:
        torch.set_num_threads(threads)
    results = summarise(config, runs)
    results["timing"] = {"wall_s": round(time.perf_counter() - started, 3)}
    return results


_CLI_FIELDS = (
    "seeds", "steps", "worlds", "methods", "out", "seed", "logger",
    "size", "obstacles", "max_steps", "layout_seed", "threads",
    "body", "sensors", "distractors", "sensor_permutation", "sensor_noise", "actuator_noise",
)  # fmt: skip


def add_parser(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``compare`` command to ``subparsers``; its options are CompareConfig's fields."""
    parser = subparsers.add_parser(
        "compare",
        help=COMPARE_HELP,
        description="Run factor-q, q-learning, dqn and factor-dqn for --seeds experiments of "
        "--steps env steps per world; write comparison.json, comparison.png and comparison.md "
        "to --out.",
    )
    docs = field_docs(CompareConfig)
    hints = typing.get_type_hints(CompareConfig)
    defaults = CompareConfig()
    for name in _CLI_FIELDS:
        default = getattr(defaults, name)
        kwargs: dict[str, Any] = {"default": argparse.SUPPRESS}
        if name in ("worlds", "methods"):
            kwargs.update(metavar="NAME[,NAME]", type=str)
            shown = ",".join(default)
        else:
            kind = hints[name]
            if typing.get_origin(kind) is not None:  # int | None -> int
                kind = next(arg for arg in typing.get_args(kind) if arg is not type(None))
            kwargs.update(metavar=name.upper(), type=kind)
            shown = default
        if name == "logger":
            kwargs["choices"] = LOGGERS
        help_text = f"{docs[name]} (default: {shown})".replace("%", "%%")  # argparse formats it
        parser.add_argument("--" + name.replace("_", "-"), help=help_text, **kwargs)
    return parser


def config_from_args(args: argparse.Namespace) -> CompareConfig:
    """A validated CompareConfig from parsed options (ValueError / TypeError when invalid)."""
    return CompareConfig(
        **{name: getattr(args, name) for name in _CLI_FIELDS if hasattr(args, name)}
    )


def main(args: argparse.Namespace | list[str] | None = None) -> int:
    """Run ``factorq compare`` from parsed ``args`` (or an argv list); return the exit status."""
    if not isinstance(args, argparse.Namespace):
        root = argparse.ArgumentParser(prog="factorq")
        parser = add_parser(root.add_subparsers(dest="command"))
        try:
            args, unknown = root.parse_known_args(
                ["compare", *(sys.argv[1:] if args is None else args)]
            )
            if unknown:  # reported by the compare parser, not the stand-in root
                parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        except SystemExit as exit_:
            return exit_.code if isinstance(exit_.code, int) else 2
    else:
        parser = None
    try:
        config = config_from_args(args)
    except (ValueError, TypeError) as error:
        prog = parser.prog if parser is not None else "factorq compare"
        print(f"{prog}: error: {error}", file=sys.stderr)
        return 2
    print(
        f"{len(config.methods)} methods x {len(config.worlds)} worlds x {config.seeds} seeds, "
        f"{config.steps:,} env steps each",
        file=sys.stderr,
    )
    bars: dict[str, Any] = {}

    def progress(method: str, done: int, total: int) -> None:
        from tqdm.auto import tqdm

        if method not in bars:
            bars[method] = tqdm(total=total, desc=f"factorq compare {method}", unit="step")
        bar = bars[method]
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    try:
        results = run(config, progress)
        paths = write_outputs(results, config.out)
    except KeyboardInterrupt:
        print("factorq compare: interrupted", file=sys.stderr)
        return 130
    print(report_markdown(results))
    for path in paths.values():
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
