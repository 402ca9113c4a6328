"""``factorq compare``: tabular Factor-Q and Q-learning, DQN and neural Factor-Q (Factor-DQN) on
the three worlds, for ``seeds`` independent experiments and a budget of ``steps`` env steps each.

    config -> for each method: one batch of (worlds x seeds) experiments -> per-episode traces
           -> steps to threshold, collisions, greedy collisions -> comparison.json / .png / .md

**Step budget.** Every experiment gets exactly ``steps`` env steps, episodes being as many as fit
(the last one may be cut by the budget: its collisions count, its path length does not). This is
not the paper's runs x episodes protocol: a budget of env steps is what makes DQN, which trains on
a replay buffer, comparable with the online methods. Tabular methods and Factor-DQN run in the
project's ``OnlineCollector`` (one run, stepped ``steps`` times), DQN in torchrl's ``Collector``
(``factorq_trainers.methods.dqn``).

**The swap.** Factor-Q and Factor-DQN run the very same code (``run_online``: env with
``SplitLocalReward``, ``FactorQPolicy`` (eqs. 2-3), ``FactorQLoss`` (eq. 4, and eq. 5 or its
regression), ``OnlineCollector``); only their ``value_providers`` differ.

**Threshold.** ``steps_to_threshold`` is the env steps at the end of the first episode whose path
length is within 1.5x the shortest path: the BFS distance from start to goal in the static layout;
in the moving worlds, where the shortest path changes with every scatter, the obstacle-free
Manhattan distance ``2 (size - 1)``. Per method and world it is the mean over seeds when every
seed reached it, ``null`` otherwise (``seeds_reached`` says how many did).

**Units.** One per method, its worlds x seeds one batch (``units``), kept in ``out/units/``
(``--resume``, ``--cluster``: the numbers of an uninterrupted run); ``wall_s`` is the batch's time,
the same for each of its worlds. **Logs** (``finish``): torchrl's ``CSVLogger`` or
``TensorboardLogger`` under ``out/logs/<method>/``, per experiment and finished episode
(``methods.experiment.log_traces``), ``loss`` being 0.5 x squared TD error (of each step's update
for the online methods, of the latest minibatch for DQN) averaged over the episode's steps.
"""

from __future__ import annotations

import functools
import math
import os
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from factorq_envs.grid_world import shortest_path_length as path_length_around
from factorq_envs.grid_world import static_layout
from factorq_torch.base.rng import STREAM_LOCAL_NETWORK, STREAM_POLICY, STREAM_TASK_NETWORK
from factorq_torch.collectors import OnlineCollector
from factorq_torch.neural import LocalRewardNetwork, TaskQNetwork
from factorq_trainers.analysis.stats import bootstrap_mean_ci, scalar_ci, seed_bands
from factorq_trainers.commands.compare.config import CompareConfig
from factorq_trainers.commands.compare.report import LOGS_DIRECTORY, THRESHOLD_FACTOR
from factorq_trainers.methods import dqn, experiment
from factorq_trainers.methods.dqn import batch_keys
from factorq_trainers.methods.units import tick, torch_threads
from factorq_trainers.runner import frame, outdir, resources
from factorq_trainers.runner.kept import COUNT, FRACTION, NON_NEGATIVE, NUMBER, TEXT

NAME = "compare"
HELP = "compare tabular Factor-Q, Q-learning, DQN and neural Factor-Q on the three worlds"
DESCRIPTION = (
    "Run factor-q, q-learning, dqn and factor-dqn for --seeds experiments of --steps env steps "
    "per world; write comparison.json, comparison.png and comparison.md to --out."
)
FILES = {"json": "comparison.json", "report": "comparison.md", "figure": "comparison.png"}
HINT = "use fewer --seeds or --steps, or a smaller --size"
WORK_UNIT = "step"
CURVE_POINTS = 100
#: A unit's result (``run_unit``), what a kept one must hold (``runner.kept``'s schema): one
#: trace per experiment, its per-episode fields as lists.
UNIT_RESULT = {
    "method": TEXT,
    "traces": [
        {
            "world": TEXT,
            "seed_index": COUNT,
            "steps": [COUNT],
            "collisions": [COUNT],
            "greedy_collisions": [COUNT],
            "task_return": [NUMBER],
            "env_steps": [COUNT],
            "epsilon": [FRACTION],
            "loss": [NON_NEGATIVE],  # 0.5 x squared TD error; null before DQN's first minibatch
            "total_collisions": COUNT,
            "total_greedy_collisions": COUNT,
            "total_boxed_in_greedy_collisions": COUNT,
            "total_env_steps": COUNT,
        }
    ],
    "wall_s": NON_NEGATIVE,
}


CONFIG = CompareConfig


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
    if method in ("q-learning", "factor-q"):
        return (*experiment.tabular_values(method, count, world), None)
    if method == "factor-dqn":
        settings = config.factor_dqn
        task = TaskQNetwork(
            count,
            cells,
            num_headings=world.num_headings,
            num_actions=world.num_actuators,
            hidden=settings.hidden,
            activation=settings.activation,
            keys=batch_keys(experiments, STREAM_TASK_NETWORK, method),
        )
        local = LocalRewardNetwork(
            count,
            dependency=world.dependency,
            hidden=settings.local_hidden,
            bias=settings.local_bias,
            activation=settings.local_activation,
            shared=settings.local_shared,
            keys=batch_keys(experiments, STREAM_LOCAL_NETWORK, method),
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


def run_online(
    method: str,
    config: CompareConfig,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Tabular Factor-Q, tabular Q-learning or Factor-DQN for the step budget (OnlineCollector).

    Returns ``{"traces", "wall_s"}`` like ``factorq_trainers.methods.dqn.run``;
    ``progress(n)``: the env steps per experiment done since its last call, every 1% of the
    budget.
    """
    started = time.perf_counter()
    experiments, agent = config.experiments, config.agent
    count, steps = experiments.num_experiments, experiments.steps
    task, local, optimizer = value_providers(method, config, count)
    epsilon = config.factor_dqn.epsilon if method == "factor-dqn" else agent.epsilon
    if local is None:  # Q-learning: no local model, uniform exploration (AgentConfig: Factor-Q's)
        agent = replace(agent, exploration="uniform", risk_gate=False)
    grid = dqn.batch_env(experiments)
    env, policy, loss = experiment.online_agent(
        grid,
        task,
        local,
        agent,
        batch_keys(experiments, STREAM_POLICY, method),
        epsilon=epsilon,
    )
    # An episode takes at least the Manhattan distance, so this many always fit the budget.
    episodes = steps // (2 * (experiments.size - 1)) + 1
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=episodes, optimizer=optimizer)
    captured: dict[str, torch.Tensor] = {}
    hook = loss.register_forward_hook(lambda module, inputs, output: captured.update(output))
    recorder = experiment.EpisodeRecorder(experiments.labels)
    for step in range(1, steps + 1):
        recorder.update(collector.step(), epsilon, 0.5 * captured["td_error"].pow(2))
        if progress is not None:
            tick(progress, step, steps, max(1, steps // 100))
    hook.remove()
    return {"traces": recorder.traces(), "wall_s": time.perf_counter() - started}


# --------------------------------------------------------------------------------------------
# Summaries


def shortest_path_length(experiments: experiment.ExperimentConfig, world: str) -> int:
    """BFS distance start -> goal in the static layout; ``2 (size - 1)`` in a moving world."""
    size = experiments.size
    if world != "static":
        return 2 * (size - 1)
    length = path_length_around(static_layout(experiments.world), size)
    if length is None:
        raise ValueError(f"the static layout (layout_seed={experiments.layout_seed}) has no path")
    return length


def steps_to_threshold(trace: dict[str, Any], threshold: float) -> int | None:
    """Env steps at the end of the first episode with path length <= ``threshold`` (or None)."""
    reached = np.flatnonzero(trace["steps"] <= threshold)
    return int(trace["env_steps"][reached[0]]) if reached.size else None


def _curve(traces: list[dict[str, Any]], name: str, grid: np.ndarray, seed: int) -> dict[str, list]:
    """Per-episode ``name`` against env steps: for every seed, the mean over the episodes that
    ended in each interval ``(grid[k-1], grid[k]]`` (the last value carried over an interval where
    none ended, NaN before the first), then the mean and 95% band across seeds (BCa bootstrap: it
    stays between the seeds, so inside the quantity's range) where every seed
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
    return seed_bands(values, seed, every_seed=True)


def summarise(config: CompareConfig, outcomes: Sequence[Any]) -> dict[str, Any]:
    """``comparison.json``'s own entries (``thresholds``, ``results``, ``curves``; the frame's
    envelope goes around them) from the units' results, in ``units`` order: every method's
    ``{"traces", "wall_s"}`` (the traces' arrays as numpy arrays or lists)."""
    runs = {unit["method"]: outcome for unit, outcome in zip(units(config), outcomes, strict=True)}
    experiments = config.experiments
    grid = np.linspace(experiments.steps / CURVE_POINTS, experiments.steps, CURVE_POINTS)
    thresholds = {}
    for world in experiments.regimes:
        shortest = shortest_path_length(experiments, world)
        thresholds[world] = {"shortest_path": shortest, "threshold": THRESHOLD_FACTOR * shortest}
    results: dict[str, Any] = {}
    curves: dict[str, Any] = {}
    for method, run in runs.items():
        results[method], curves[method] = {}, {}
        for world in experiments.regimes:
            traces = [_arrays(trace) for trace in run["traces"] if trace["world"] == world]
            reached = [steps_to_threshold(t, thresholds[world]["threshold"]) for t in traces]
            hit = [value for value in reached if value is not None]
            bounded = functools.partial(bootstrap_mean_ci, seed=experiments.seed)  # counts: >= 0
            collisions = scalar_ci([t["total_collisions"] for t in traces], bounded)
            greedy_counts = [t["total_greedy_collisions"] for t in traces]
            boxed_in = [t["total_boxed_in_greedy_collisions"] for t in traces]
            greedy = scalar_ci(greedy_counts, bounded)
            avoidable = scalar_ci(np.subtract(greedy_counts, boxed_in), bounded)
            tail = [t["steps"][t["env_steps"] > 0.8 * experiments.steps] for t in traces]
            tail = [float(values.mean()) for values in tail if values.size]
            wall_s = run["wall_s"]
            results[method][world] = {
                "steps_to_threshold": float(np.mean(hit)) if len(hit) == len(traces) else None,
                "collisions": collisions[0],
                "greedy_collisions": greedy[0],
                "wall_s": None if wall_s is None else round(float(wall_s), 3),
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
                name: _curve(traces, name, grid, experiments.seed)
                for name in ("steps", "collisions")
            }
    return {
        "thresholds": thresholds,
        "results": results,
        "curves": {"env_steps": [float(x) for x in grid], **curves},
    }


def _arrays(trace: dict[str, Any]) -> dict[str, Any]:
    """A trace with its per-episode fields as numpy arrays (a kept unit holds lists; a missing
    float, written as null, is NaN again)."""
    arrays = dict(trace)
    fields = [name for name in experiment.EPISODE_FIELDS if name in trace]
    for name in fields:
        values = trace[name]
        if not isinstance(values, np.ndarray):
            values = [math.nan if value is None else value for value in values]
        arrays[name] = np.asarray(
            values, dtype=np.float64 if name in experiment.FLOAT_FIELDS else np.int64
        )
    return arrays


def check_unit(config: CompareConfig, unit: dict[str, Any], result: dict[str, Any]) -> str | None:
    """Why a kept ``result`` (``UNIT_RESULT``'s shape) cannot be ``unit``'s, or None: one trace
    per experiment of the run, in its order, each with per-episode fields of one length."""
    experiments = config.experiments
    labels = [(trace["world"], trace["seed_index"]) for trace in result["traces"]]
    if labels != [tuple(label) for label in experiments.labels]:
        return (
            f"its traces are of the experiments {labels}, not this run's {list(experiments.labels)}"
        )
    for trace in result["traces"]:
        lengths = {len(trace[name]) for name in experiment.EPISODE_FIELDS if name in trace}
        if len(lengths) > 1:
            return (
                f"a trace of {trace['world']}, seed {trace['seed_index']}, has per-episode "
                f"fields of different lengths {sorted(lengths)}"
            )
    return None


# --------------------------------------------------------------------------------------------
# The command: a unit per method


def units(config: CompareConfig) -> list[dict[str, Any]]:
    """One unit per method: its worlds x seeds are one batch (DQN's seeds and worlds share
    torch's stream and every minibatch, so a smaller unit would change its numbers)."""
    return [{"id": method, "method": method} for method in config.methods]


def work(config: CompareConfig, unit: dict[str, Any]) -> int:
    """A unit's env steps per experiment (what ``run_unit`` reports to ``progress``)."""
    return config.steps


def estimate(config: CompareConfig) -> resources.Estimate:
    """Peak memory of ``factorq compare`` with ``config`` (a ``CompareConfig``): the largest
    method's tables, networks and replay buffer, and every method's per-episode records (kept
    until the summary, as each unit's result; counted as if every episode were as short as
    possible)."""
    experiments = config.experiments
    count = experiments.num_experiments
    world = experiments.world
    cells = experiments.size**2 * world.num_headings
    sensors, actions = world.num_sensors, world.num_actuators
    # An episode takes at least the Manhattan distance: at most this many fit the budget.
    episodes = experiments.steps // (2 * (experiments.size - 1)) + 1
    # Per episode: 7 records as Python floats in lists, their numpy copies, the collector's
    # metrics [E, 1, episodes] (4 x 8 bytes).
    records = count * episodes * (7 * 32 + 7 * 8 + 32)
    largest: dict[str, int] = {}
    for method in config.methods:
        parts: dict[str, int] = {}
        if method == "q-learning":
            parts["tables"] = count * (cells << sensors) * actions * 4
        elif method == "factor-q":
            parts["tables"] = count * (cells * actions * 4 + actions * (2 << sensors) * 12)
        elif method == "factor-dqn":
            neural = config.factor_dqn
            weights = _mlp_weights(cells, neural.hidden, actions)
            copies = 1 if neural.local_shared else actions
            weights += _mlp_weights(sensors, neural.local_hidden, 1) * copies
            # weights, gradients, Adam's two moments; activations of one step
            parts["networks"] = count * (4 * weights * 4 + 4 * (cells + sum(neural.hidden)) * 3)
        else:  # dqn
            settings = config.dqn
            weights = _mlp_weights(cells + sensors, settings.hidden, actions)
            width = cells + sensors + sum(settings.hidden) + actions
            parts["networks"] = count * 5 * weights * 4  # + gradients, Adam moments, target copy
            # A minibatch [B, E]: its one-hot features and activations, forward and backward,
            # for the network and the target network.
            parts["minibatch"] = settings.batch_size * count * width * 4 * 3
            # One row [E] of 38 bytes per stored transition, and the collector's batch of
            # train_every steps of every experiment (all of a step's entries, ~200 bytes each).
            parts["replay buffer"] = min(settings.buffer_size, experiments.steps) * count * 38
            parts["collector"] = settings.train_every * count * (200 + 4 * width)
        parts["env"] = count * (cells + resources.EXPERIMENT_BYTES)
        if sum(parts.values()) > sum(largest.values()):
            largest = parts
    largest["episode records"] = records * len(config.methods)
    largest["curves"] = len(config.methods) * len(experiments.regimes) * 100 * 6 * 56
    return resources.Estimate(
        largest, len(config.methods) * count * experiments.steps, exact_steps=True
    )


def _mlp_weights(inputs: int, hidden: tuple[int, ...], outputs: int) -> int:
    """Weights and biases of one MLP ``inputs -> hidden... -> outputs``."""
    widths = [inputs, *hidden, outputs]
    return sum(a * b + b for a, b in zip(widths, widths[1:], strict=False))


def run_unit(
    config: CompareConfig, unit: dict[str, Any], progress: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """One method's batch (all selected worlds and seeds) with ``config.threads`` torch threads:
    ``{"method", "traces", "wall_s"}`` (the traces' arrays are lists once the frame's JSON has
    them, as every unit's result is kept and read back). A method's numbers do not
    depend on the others (DQN seeds torch's global stream first): methods may run in any order,
    in any process.

    Args:
        progress: called with the env steps per experiment done since its last call.
    """
    method = unit["method"]
    with torch_threads(config.threads):
        if method == "dqn":
            run = dqn.run(config.dqn, config.experiments, progress=progress)
        else:
            run = run_online(method, config, progress=progress)
    return {"method": method, "traces": run["traces"], "wall_s": run["wall_s"]}


def finish(config: CompareConfig, outcomes: list[Any], out: Path) -> dict[str, Path]:
    """Every method's per-episode logs (``config.logger``'s), written once the run is over from
    the units' traces to a staging folder renamed to ``out/logs`` (an earlier run's logs replaced,
    never appended to): one run's logs, the same after a resume."""
    if config.logger == "tensorboard":
        from torchrl.record.loggers.tensorboard import TensorboardLogger as Logger
    else:
        from torchrl.record.loggers.csv import CSVLogger as Logger
    # a fresh folder, named like the temporaries ``runner.outdir`` cleans up after a kill
    staging = out / outdir.temporary_name(LOGS_DIRECTORY)
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    try:
        for unit, outcome in zip(units(config), outcomes, strict=True):
            logger = Logger(exp_name=unit["method"], log_dir=str(staging))
            experiment.log_traces(logger, [_arrays(trace) for trace in outcome["traces"]])
        target = out / LOGS_DIRECTORY
        if target.exists():  # moved aside and deleted first: the logs of two runs never mix
            old = out / outdir.temporary_name(f"{LOGS_DIRECTORY}.old")
            os.replace(target, old)
            shutil.rmtree(old, ignore_errors=True)
        os.replace(staging, target)
        return {"logs": target}
    finally:
        shutil.rmtree(staging, ignore_errors=True)  # renamed away unless writing failed


def run(config: CompareConfig, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Every selected method on every selected world, here; the ``comparison.json`` dict (no
    files written; ``progress``: env steps per experiment done since its last call)."""
    return frame.run_in_process(sys.modules[__name__], config, progress)
