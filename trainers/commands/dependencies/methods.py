"""``factorq dependencies``' methods, one setting at a time: the learned structure (compiled or
modular), the compiled oracle, joint table and Q-learning, the gated network and DQN, each on
the same worlds and the learner's sensor orders (see ``command.py`` beside it).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from factorq_envs.regimes import REGIME_PERIODS
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD
from factorq_torch.base.validation import MAX_PARENTS, MAX_TABLE_ENTRIES
from factorq_trainers.commands.dependencies.config import (
    CURVE_EVERY,
    GATED_L1,
    GATED_LEARNING_RATE,
    KEYED_METHODS,
    STREAM_ORDER,
    DependenciesConfig,
)
from factorq_trainers.compiled import fast
from factorq_trainers.methods.experiment import experiment_keys, make_env, online_agent


def sensor_orders(
    seed: int, setting_stream: int, count: int, num_sensors: int, redraw: int
) -> torch.Tensor:
    """``[count, K]``: experiment ``i``'s sensor order (``redraw`` 0: the first, 1: after the
    change), drawn from its own generator seeded by ``(seed, setting_stream, i, redraw)``
    (``setting_stream``: ``DependenciesConfig.setting_stream``, from the setting's content)."""
    orders = []
    for index in range(count):
        generator = torch.Generator().manual_seed(
            hash((seed, STREAM_ORDER, setting_stream, index, redraw)) & (2**63 - 1)
        )
        orders.append(torch.randperm(num_sensors, generator=generator))
    return torch.stack(orders)


def _orders(config: DependenciesConfig, setting: str, redraw: int) -> torch.Tensor:
    """``sensor_orders`` of ``setting``'s experiments (``redraw`` 1: after the change)."""
    num_sensors = config.world_of(setting).num_sensors
    return sensor_orders(config.seed, config.setting_stream(setting), config.seeds, num_sensors,
                         redraw)  # fmt: skip


def _orders_after(config: DependenciesConfig, setting: str) -> torch.Tensor | None:
    """The orders after the change in the ``change`` setting, else None."""
    return _orders(config, setting, 1) if setting == "change" else None


def _keys(config: DependenciesConfig, method: str) -> tuple[torch.Tensor, torch.Tensor]:
    labels = [(config.regime, index) for index in range(config.seeds)]
    world_keys = experiment_keys(config.seed, STREAM_WORLD, labels)
    return world_keys, experiment_keys(config.seed, STREAM_POLICY, labels, KEYED_METHODS, method)


def _periods(config: DependenciesConfig) -> torch.Tensor:
    return torch.full((config.seeds,), REGIME_PERIODS[config.regime], dtype=torch.int64)


#: The options ``StructureLearner`` and ``fast.StructureOptions`` take as the config names them.
LEARNER_OPTIONS = tuple(
    "max_parents bayes_factor window prior_a prior_b prediction reopen reopen_factor "
    "noisy_reopen_factor likelihood pairs".split()
)


def _learner_options(config: DependenciesConfig) -> dict[str, Any]:
    """The learner's options (``candidate_prior`` is its ``prior``)."""
    options = {name: getattr(config, name) for name in LEARNER_OPTIONS}
    return {**options, "prior": config.candidate_prior}


def run_learned(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """The learned structure with its structure metrics: on the compiled path where it runs
    (``fast.StructureOptions``), else on the modular torchrl path (``run_learned_modular``);
    both give the same numbers bit for bit (``tests/test_fast_structure.py``)."""
    world = config.world_of(setting)
    if (
        config.path == "modular"
        or config.prediction == "posterior"
        or not fast.is_available()
        or fast.unsupported_reason(world) is not None
    ):
        return run_learned_modular(config, setting)
    return run_learned_fast(config, setting)


def run_learned_fast(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """``run_learned`` on the compiled path."""
    from factorq_envs.permutation import permuted_dependency

    world = config.world_of(setting)
    world_keys, policy_keys = _keys(config, "factor-q-learned")
    orders, orders_after = _orders(config, setting, 0), _orders_after(config, setting)
    options = fast.StructureOptions(
        orders=orders,
        orders_after=orders_after,
        change_run=0 if orders_after is None else config.change_run,
        curve_every=CURVE_EVERY,
        **_learner_options(config),
    )
    batch = fast.ExperimentBatch(
        "factor-q", _periods(config), world, config.agent_of("factor-q-learned"), config.runs,
        config.episodes, world_keys, policy_keys, threads=config.threads, structure=options,
    )  # fmt: skip
    metrics = batch.run()
    state = batch.learner_state()
    sets = batch._candidate_sets
    members = torch.zeros(len(sets), world.num_sensors, dtype=torch.bool)
    for index, parents in enumerate(sets):
        members[index, list(parents)] = True
    committed = state["committed"]
    structure = members[committed.clamp(min=0)] & (committed >= 0).unsqueeze(-1)
    truth = permuted_dependency(world.dependency, orders if orders_after is None else orders_after)
    curve = _fill_curve(state["curve"], metrics["steps"].sum(dim=(1, 2)))
    return _structure_result(setting, metrics, structure, truth, curve, state)


def _fill_curve(curve: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """``[S, points]`` bool: an experiment that has finished holds its last point; the points
    stop at the longest experiment's end."""
    curve = curve[:, : int(steps.max()) // CURVE_EVERY + 1]
    points = torch.arange(curve.shape[1]) * CURVE_EVERY
    last = (steps // CURVE_EVERY).clamp(max=curve.shape[1] - 1)  # [S]
    final = curve.gather(1, last.unsqueeze(1))  # [S, 1]
    return torch.where(points <= steps.unsqueeze(1), curve, final).bool()


def _structure_result(
    setting: str,
    metrics: dict[str, torch.Tensor],
    structure: torch.Tensor,
    truth: torch.Tensor,
    curve: torch.Tensor,
    state: dict[str, Any],
) -> dict[str, Any]:
    """The learner's structure metrics from its ``structure`` and the ``truth`` at the end
    ``[S, A, K]``, its ``curve`` and its ``state`` (``right_since``, ``samples_at_change``,
    ``wrong_commitments``, ``reopened``, ``samples``: both paths keep them)."""
    right_since, samples_at_change = state["right_since"], state["samples_at_change"]
    wrong_commitments, reopened, samples = (
        state[name] for name in ("wrong_commitments", "reopened", "samples")
    )
    right = (structure == truth).all(dim=-1)  # [S, A]
    final_right = right.all(dim=-1)
    since = right_since - (samples_at_change if setting == "change" else 0)
    since = since.clamp(min=0).to(torch.float64)
    until_right = torch.where(final_right, since.max(dim=-1).values, math.inf)
    hamming = (structure != truth).sum(dim=(1, 2))
    points = curve.shape[1]
    fraction = curve.float().mean(dim=0)
    return {
        "metrics": metrics,
        "samples_until_right": until_right.tolist(),
        "wrong_commitments": wrong_commitments.tolist(),
        "hamming_at_end": hamming.tolist(),
        "reopened": reopened.sum(dim=-1).tolist(),
        "samples_per_actuator": samples.tolist(),
        "curve": {
            "env_steps": [CURVE_EVERY * point for point in range(points)],
            "fraction_right": fraction.tolist(),
        },
        "_curve": curve,
        "_state": state,
    }


def _permuted_collector(
    config: DependenciesConfig, setting: str, local: Any, optimizer: Any = None
) -> tuple[Any, torch.Tensor, Callable[[], torch.Tensor]]:
    """``(collector, truth, redraw)``: Factor-Q's ``OnlineCollector`` on the modular path around
    the provider ``local``, the sensors in the learner's orders, the true dependency in them
    ``[S, A, K]``, and ``redraw()``, called after each step, which redraws the orders (and the
    truth, in place) of the experiments that reached run ``change_run`` in the change setting and
    returns them ``[S]``. The policy stream is the learned structure's (the gated network's too:
    common random numbers, ``KEYED_METHODS``)."""
    from factorq_envs.permutation import PermuteSensors, permuted_dependency
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.tables import TaskQTable

    world, count = config.world_of(setting), config.seeds
    world_keys, policy_keys = _keys(config, "factor-q-learned")
    orders = _orders(config, setting, 0)
    permute = PermuteSensors(orders)
    task = TaskQTable(
        count, world.num_cells, num_headings=world.num_headings, num_actions=world.num_actuators
    )
    base = make_env(world, _periods(config), world_keys)
    agent = config.agent_of("factor-q-learned")  # the gated network's too
    env, policy, loss = online_agent(base, task, local, agent, policy_keys)
    env.append_transform(permute)  # after the split reward, as the compiled path reads them
    collector = OnlineCollector(
        env, policy, loss, runs=config.runs, episodes=config.episodes, optimizer=optimizer
    )
    truth = permuted_dependency(world.dependency, orders)
    changed = torch.zeros(count, dtype=torch.bool)

    def redraw() -> torch.Tensor:
        due = (collector.run_index >= config.change_run) & ~changed
        if setting != "change" or not bool(due.any()):
            return torch.zeros_like(changed)
        new_orders = _orders(config, setting, 1)
        permute.set_permutations(new_orders, due)
        truth[due] = permuted_dependency(world.dependency, new_orders)[due]
        changed[due] = True
        return due

    return collector, truth, redraw


def run_learned_modular(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """``run_learned`` on the modular torchrl path: ``StructureLearner`` through
    ``FactorQPolicy``, ``FactorQLoss`` and ``OnlineCollector``."""
    from factorq_torch.structure import StructureLearner

    world, count = config.world_of(setting), config.seeds
    learner = StructureLearner(
        count, num_actions=world.num_actuators, num_sensors=world.num_sensors,
        **_learner_options(config),
    )  # fmt: skip
    collector, truth, redraw = _permuted_collector(config, setting, learner)
    actuators = world.num_actuators
    right_since = torch.full((count, actuators), -1)  # samples when it last became right
    samples_at_change = torch.zeros(count, actuators, dtype=torch.int64)
    wrong_commitments = torch.zeros(count, dtype=torch.int64)
    previous = learner.committed.clone()
    steps = torch.zeros(count, dtype=torch.int64)
    max_steps = config.runs * config.episodes * world.max_steps
    curve = torch.zeros(count, max_steps // CURVE_EVERY + 1, dtype=torch.uint8)
    rows = torch.arange(count)
    for td in collector:
        active = td.get(("collector", "mask"))
        steps += active.to(torch.int64)
        due = redraw()
        samples_at_change[due] = learner.samples[due]
        right = (learner.structure() == truth).all(dim=-1)  # [S, A]
        right_since = torch.where(
            right, torch.where(right_since < 0, learner.samples, right_since), -1
        )
        committed = learner.committed
        new_commit = (committed >= 0) & (committed != previous)
        wrong_commitments += (new_commit & ~right).sum(dim=-1)
        previous = committed.clone()
        point = active & (steps % CURVE_EVERY == 0)
        curve[rows[point], steps[point] // CURVE_EVERY] = right.all(dim=-1)[point].to(torch.uint8)
    metrics = {name: collector.metrics.get(name) for name in collector.metrics.keys()}
    # the learner's state as the compiled path keeps it (``fast.ExperimentBatch.learner_state``)
    counts = ("count", "successes", "reward_sum", "log_marginal")
    cloned = ("committed", "samples", "block_samples", "reopened", "map_cache", "history_length")
    state = {name: getattr(learner, name).clone() for name in (*cloned, *counts)}
    state.update({f"block_{name}": getattr(learner, f"block_{name}").clone() for name in counts})
    state.update(
        plausible=learner.plausible_cache.to(torch.uint8),
        active=learner.active.to(torch.uint8),
        right_since=right_since,
        samples_at_change=samples_at_change,
        wrong_commitments=wrong_commitments,
        noise_seen=learner.noise_seen.to(torch.int64),
    )
    curve = _fill_curve(curve, steps)
    return _structure_result(setting, metrics, learner.structure(), truth, curve, state)


def run_compiled(config: DependenciesConfig, setting: str, method: str) -> dict[str, Any]:
    """The oracle, the joint table or Q-learning on the compiled path (a method that does not
    fit or cannot run the setting never gets here: ``skipped_reason``)."""
    world = config.world_of(setting)
    world_keys, policy_keys = _keys(config, method)
    dependency, orders = None, None
    if method == "factor-q-joint":
        dependency = torch.ones(world.num_actuators, world.num_sensors, dtype=torch.bool)
    if method in ("factor-q-joint", "q-learning"):  # the learner's sensor orders, changed alike
        after = _orders_after(config, setting)
        change_run = 0 if after is None else config.change_run
        orders = fast.SensorOrders(_orders(config, setting, 0), after, change_run)
    metrics = fast.run_experiments(
        "q-learning" if method == "q-learning" else "factor-q", _periods(config), world,
        config.agent_of(method), config.runs, config.episodes, world_keys, policy_keys,
        threads=config.threads, dependency=dependency, sensor_orders=orders,
    )  # fmt: skip
    return {"metrics": metrics}


def run_gated(config: DependenciesConfig, setting: str) -> dict[str, Any]:
    """Factor-Q with ``GatedLocalRewardNetwork`` (one network per experiment and actuator over
    all sensors, sigmoid gates under an L1 penalty, Adam) through ``FactorQPolicy``,
    ``FactorQLoss`` and ``OnlineCollector``, the sensors in the learner's orders (the change
    setting: redrawn at the same run). Its structure is read at the end (``structure()``: a
    sensor is a parent when flipping it moves the predicted local reward by a quarter of a
    collision), against the truth of that moment."""
    from factorq_torch.neural import GatedLocalRewardNetwork

    world = config.world_of(setting)
    local = GatedLocalRewardNetwork(
        config.seeds, num_actions=world.num_actuators, num_sensors=world.num_sensors, l1=GATED_L1,
        seed=config.seed,
    )  # fmt: skip
    optimizer = torch.optim.Adam(local.parameters(), lr=GATED_LEARNING_RATE)
    collector, truth, redraw = _permuted_collector(config, setting, local, optimizer)
    for _ in collector:
        redraw()
    structure = local.structure()  # [S, A, K]
    metrics = {name: collector.metrics.get(name) for name in collector.metrics.keys()}
    return {
        "metrics": metrics,
        "right_at_end": (structure == truth).all(dim=-1).all(dim=-1).tolist(),
        "hamming_at_end": (structure != truth).sum(dim=(1, 2)).tolist(),
    }


def _budget(config: DependenciesConfig, setting: str, runs: dict[str, dict[str, Any]]) -> int:
    """DQN's step budget: the oracle's mean env steps per experiment (else the learned
    structure's, else every episode at its longest)."""
    for method in ("factor-q", "factor-q-learned"):
        if method in runs:
            steps = runs[method]["metrics"]["steps"].sum(dim=(1, 2)).double().mean()
            return max(1, round(float(steps)))
    return config.runs * config.episodes * config.world_of(setting).max_steps


def run_dqn(config: DependenciesConfig, setting: str, budget: int) -> dict[str, Any]:
    """DQN (``methods.dqn``, its default hyperparameters) on the setting's worlds for
    ``budget`` env steps per experiment (episodes as many as fit; DQN has no runs). It sees every
    sensor (``TaskQNetwork(with_proximity=True)``); the order does not matter to a network trained
    from scratch, so it runs without ``PermuteSensors``. Measured cost: 100 experiments of 1,400
    steps took 300 s on 2 loaded cores (docs/decisions.md), hence opt-in."""
    from factorq_trainers.methods import dqn
    from factorq_trainers.methods.experiment import ExperimentConfig

    shared = ("seed", "seeds", "size", "obstacles", "max_steps", "layout_seed")
    experiments = ExperimentConfig(
        **{name: getattr(config, name) for name in shared},
        regimes=(config.regime,),
        steps=budget,
        **config.body_of(setting),
    )
    traces = dqn.run(dqn.DQNConfig(), experiments)["traces"]
    episodes = min(len(trace["steps"]) for trace in traces)
    return {
        "totals": {
            "collisions": np.array([trace["total_collisions"] for trace in traces], float),
            "greedy": np.array([trace["total_greedy_collisions"] for trace in traces], float),
        },
        "budget": budget,
        "episodes": [len(trace["steps"]) for trace in traces],
        "collisions_per_episode": [
            float(np.mean([trace["collisions"][index] for trace in traces]))
            for index in range(episodes)
        ],
    }


def skipped_reason(config: DependenciesConfig, setting: str, method: str) -> str | None:
    """Why ``method`` does not run in ``setting`` (``None``: it runs)."""
    world = config.world_of(setting)
    if method in ("factor-q-learned", "factor-q-gated"):
        return None
    if method == "dqn":
        if setting == "change":
            return (
                "DQN's env (factorq_trainers.methods.dqn) cannot change the sensor order "
                "mid-experiment"
            )
        return None
    if not fast.is_available():
        return f"the compiled path is unavailable ({fast.unavailable_reason()})"
    if method == "factor-q-joint" and world.num_sensors > MAX_PARENTS:
        return (
            f"a joint table over {world.num_sensors} sensors needs 2**{world.num_sensors} "
            f"entries per actuator, past the cap of 2**{MAX_PARENTS}"
        )
    if method == "q-learning":
        entries = (world.num_cells * world.num_headings << world.num_sensors) * world.num_actuators
        if entries > MAX_TABLE_ENTRIES:
            return f"its table needs {entries} values per experiment, past 2**24"
    return None
