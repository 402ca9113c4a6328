"""``factorq minigrid``'s methods, each running all seeds of one method at one size: the keys
(common random numbers: every method meets the same worlds at a size), the ``Tally`` of each
seed, the tabular agents through ``OnlineCollector`` and torchrl's DQN
(``RUNNERS``: method -> its function). The command is
``factorq_trainers.commands.minigrid.command``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from factorq_trainers.commands.minigrid.config import (
    METHODS,
    SIZE_NAMES,
    SUCCESS_THRESHOLD,
    MiniGridConfig,
)
from factorq_trainers.methods import units
from factorq_trainers.methods.units import Tally

if TYPE_CHECKING:
    import torch

    from factorq_envs.declared_env import DeclaredEnv


# --------------------------------------------------------------------------------------------
# Keys: common random numbers (every method meets the same worlds at a size)


def world_seeds(config: MiniGridConfig, size: int) -> list[int]:
    """MiniGrid's reset seed of each experiment at ``size`` (the same for every method)."""
    from factorq_torch.base.rng import STREAM_WORLD, derive_keys

    offset = SIZE_NAMES.index(str(size)) * config.seeds
    keys = derive_keys(config.seed, STREAM_WORLD, config.seeds, offset)
    return [int(key) & 0x7FFFFFFF for key in keys.tolist()]


def method_keys(config: MiniGridConfig, size: int, method: str, stream: int) -> torch.Tensor:
    """Keys ``[S]`` of ``stream`` for ``method``'s experiments at ``size``.

    Args:
        stream: a stream of ``factorq_torch.base.rng``.
    """
    from factorq_torch.base.rng import derive_keys

    slot = SIZE_NAMES.index(str(size)) * len(METHODS) + METHODS.index(method)
    return derive_keys(config.seed, stream, config.seeds, slot * config.seeds)


# --------------------------------------------------------------------------------------------
# The summary


def summary(
    tallies: list[Tally], budget: int, final_fraction: float, wall_s: float
) -> dict[str, Any]:
    """Per-seed measures (the command's docstring; ``None`` where there is nothing to measure)
    and the wall time of the seeds together.

    Args:
        budget: the env steps each seed ran.
        final_fraction: the share of the budget, at its end, of the final measures.
        wall_s: the seconds the method took for all seeds.
    """
    start = budget - final_fraction * budget
    names = ("success_rate", "return", "steps_to_goal", "episodes", "steps_to_90")
    out: dict[str, list[Any]] = {name: [] for name in names}
    for tally in tallies:
        final = [e for e in tally.episodes if e[0] > start]  # (end step, return, success, length)
        out["episodes"].append(len(tally.episodes))
        out["success_rate"].append(float(np.mean([e[2] for e in final])) if final else None)
        out["return"].append(float(np.mean([e[1] for e in final])) if final else None)
        lengths = [e[3] for e in final if e[2]]
        out["steps_to_goal"].append(float(np.mean(lengths)) if lengths else None)
        out["steps_to_90"].append(tally.reached)
    out["collisions"] = [tally.collisions for tally in tallies]
    out["greedy_collisions"] = [tally.greedy_collisions for tally in tallies]
    return {**out, "wall_s": wall_s}


# --------------------------------------------------------------------------------------------
# The methods


def _env(config: MiniGridConfig, size: int, *, with_image: bool = False) -> DeclaredEnv:
    from factorq_envs.minigrid_torchrl import MiniGridEnv

    return MiniGridEnv(
        size,
        config.semantics,
        layout=config.layout,
        with_image=with_image,
        seeds=world_seeds(config, size),
    )


def run_tabular(
    config: MiniGridConfig, size: int, method: str, tick: Callable[[int], None]
) -> dict[str, Any]:
    """Factor-Q (learned or oracle) or Q-learning through ``OnlineCollector``.

    Args:
        method: a tabular one of ``METHODS``.
    """
    import torch

    from factorq_envs.minigrid_adapter import FORWARD
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.structure import StructureLearner
    from factorq_trainers.methods.experiment import online_agent, tabular_values

    count, budget = config.seeds, config.budget(size)
    base = _env(config, size)
    algorithm = "q-learning" if method == "q-learning" else "factor-q"
    task, local = tabular_values(algorithm, count, base)  # the oracle's table for factor-q
    learner = None
    if method.startswith("factor-q-"):  # learned: an open actuator predicts no local reward
        # (docs/decisions.md, MiniGrid), unless asked for the learner's own posterior
        prediction = "posterior" if method == "factor-q-posterior" else "committed"
        local = learner = StructureLearner(
            count, num_actions=base.num_actions, num_sensors=base.num_sensors, prediction=prediction
        )
    agent = AgentConfig(exploration="uniform" if local is None else config.exploration)
    keys = method_keys(config, size, method, STREAM_POLICY)
    env, policy, loss = online_agent(base, task, local, agent, keys)
    # one run of as many episodes as the budget could hold: the loop below stops at the budget
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=budget)
    tallies = [Tally(config.window, SUCCESS_THRESHOLD) for _ in range(count)]
    assert base.dependency is not None  # MiniGrid's declaration states its oracle
    truth = base.dependency[FORWARD]  # [K]
    found: list[int | None] = [None] * count
    started = time.perf_counter()
    for step, td in enumerate(collector, start=1):
        units.record(tallies, td)
        if learner is not None:
            right = (learner.structure()[:, FORWARD] == truth).all(dim=-1).tolist()
            found = [step if ok and at is None else at for at, ok in zip(found, right, strict=True)]
        units.tick(tick, step, budget)
        if step >= budget:
            break
    wall = time.perf_counter() - started
    collector.shutdown()
    result = summary(tallies, budget, config.final_fraction, wall)
    if learner is not None:
        result["found_forward_front"] = found
        result["structure_at_end"] = learner.structure().to(torch.int64).tolist()
    return result


def run_dqn(
    config: MiniGridConfig, size: int, method: str, tick: Callable[[int], None]
) -> dict[str, Any]:
    """``factorq_trainers.methods.dqn``'s DQN (its defaults) on the cell/heading/sensors or on
    the image.

    Args:
        method: ``"dqn"`` or ``"dqn-image"``.
    """

    from factorq_envs.body import HEADING
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_TASK_NETWORK
    from factorq_torch.neural import TaskQNetwork
    from factorq_trainers.methods.dqn import DQNConfig, observation_network, train_stepwise

    dqn = DQNConfig()
    count, budget = config.seeds, config.budget(size)
    image = method == "dqn-image"
    env = _env(config, size, with_image=image)
    actions = env.num_actions
    init_keys = method_keys(config, size, method, STREAM_TASK_NETWORK)
    if image:
        q_network = observation_network(count, "image", (7, 7, 3), actions, dqn.hidden, init_keys)
        observed = ["image"]
    else:
        q_network = TaskQNetwork(
            count,
            env.num_cells,
            with_proximity=True,
            num_sensors=env.num_sensors,
            num_headings=HEADING.num_headings,
            num_actions=actions,
            hidden=dqn.hidden,
            keys=init_keys,
            zero_output=False,
        )
        observed = ["cell", "heading", "sensors"]
    tallies = [Tally(config.window, SUCCESS_THRESHOLD) for _ in range(count)]

    def on_step(td: Any, step: int) -> None:
        units.record(tallies, td)
        units.tick(tick, step, budget)

    seed = int(method_keys(config, size, method, STREAM_POLICY)[0]) & 0x7FFFFFFF
    _, wall = train_stepwise(env, q_network, dqn, budget, observed, on_step, seed)
    env.close()
    return summary(tallies, budget, config.final_fraction, wall)


RUNNERS = {
    "factor-q-learned": run_tabular,
    "factor-q-posterior": run_tabular,
    "factor-q": run_tabular,
    "q-learning": run_tabular,
    "dqn": run_dqn,
    "dqn-image": run_dqn,
}
