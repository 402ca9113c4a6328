"""Positive local rewards (issue 40, item 2): Factor-Q and Q-learning in a grid that pays.

The world is ``factorq_envs.paying_grid.PayingGrid``: the paper's 10x10 grid and obstacles, plus
items on the floor that pay ``+1`` to the actuator that moves onto one (a collision still costs
-1). Three agents learn online, one experiment per master seed, all seeds side by side in one
batch:

- ``factor-q``: local tables told the dependency (actuator ``a`` reads its proximity
  sensor and its item sensor);
- ``factor-q-learned``: the structure learner, one channel per sign
  (``SignedStructureLearner``), told nothing but the numbers of actuators and sensors;
- ``q-learning``: a Q-table over cell x the pattern of all eight sensors, on the conventional
  reward (task + local rewards).

Printed: per method, the median [min, max] over the master seeds of the items collected and the
collisions in the first episodes, the steps per episode in the last ones, and (learned) the
structures found. Written: a figure of items and steps per episode (``--figure``).

Run: ``python examples/positive_rewards.py --seeds 10 --episodes 40 --figure positive.png``
(about a minute on one core; ``docs/tutorials/positive-rewards.md`` shows the figure).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv

from factorq_envs.paying_grid import PayingConfig, PayingGrid
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_envs.transforms import SplitLocalReward
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.signed_structure import SignedStructureLearner
from factorq_torch.tables import LocalRewardTable, TaskQTable

METHODS = ("factor-q", "factor-q-learned", "q-learning")


def seed_keys(seeds: list[int], stream: int) -> torch.Tensor:
    """One key per master seed: experiment ``i`` of the batch is master seed ``seeds[i]``."""
    return torch.cat([derive_keys(seed, stream, 1) for seed in seeds])


def agent(method: str, world: PayingGrid, seeds: list[int], period: int) -> tuple:
    """``(env, policy, loss, local)`` of ``method``, one experiment per seed."""
    config, count, settings = world.config, len(seeds), AgentConfig()
    env = FactoredGridEnv(
        world=world,
        obstacle_period=period,
        batch_size=(count,),
        world_keys=seed_keys(seeds, STREAM_WORLD),
    )
    factorq = method != "q-learning"
    task = TaskQTable(
        count,
        config.num_cells,
        with_sensors=not factorq,
        num_sensors=config.num_sensors,
        num_actions=config.num_actuators,
        sparse_grad=True,
    )
    keys = seed_keys(seeds, STREAM_POLICY)
    if not factorq:
        chooser = EpsilonGreedyPolicy(count, keys=keys, epsilon=settings.epsilon)
        loss = TabularQLoss(task, gamma=settings.gamma, alpha=settings.alpha)
        return env, TensorDictSequential(task, chooser), loss, None
    if method == "factor-q":
        local = LocalRewardTable(count, dependency=world.dependency)
    else:
        local = SignedStructureLearner(
            count, num_actions=config.num_actuators, num_sensors=config.num_sensors
        )
    chooser = FactorQPolicy(
        count, keys=keys, epsilon=settings.epsilon, eta=settings.eta, g_min=settings.g_min
    )
    loss = FactorQLoss(
        task, local, gamma=settings.gamma, alpha=settings.alpha, eta=settings.eta,
        g_min=settings.g_min,
    )  # fmt: skip
    env = TransformedEnv(env, SplitLocalReward())
    return env, TensorDictSequential(task, local, chooser), loss, local


def run(method: str, world: PayingGrid, seeds: list[int], episodes: int, period: int) -> dict:
    """Per experiment and episode ``[S, episodes]``: items collected, steps with an item in
    sight (``offered``), collisions, steps; and the
    learner's structure (``[S, A, K]`` bool) for the learned method."""
    env, policy, loss, local = agent(method, world, seeds, period)
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=episodes)
    items = torch.zeros(len(seeds), episodes, dtype=torch.int64)
    offered = torch.zeros_like(items)
    rows = torch.arange(len(seeds))
    for td in collector:  # every step, after its update: count the items each one collected
        active = td["collector", "mask"]
        collected = (td["next", "collision"] > 0).any(dim=-1) & active
        sensed = td["sensors"][:, 4:].any(dim=-1) & active  # an item next to it, before acting
        episode = td["collector", "episode"].clamp(max=episodes - 1)
        items.index_put_((rows, episode), collected.to(torch.int64), accumulate=True)
        offered.index_put_((rows, episode), sensed.to(torch.int64), accumulate=True)
    metrics = collector.metrics
    out = {
        "items": items,
        "offered": offered,
        "collisions": metrics["collisions"][:, 0].clone(),
        "steps": metrics["steps"][:, 0].clone(),
    }
    if isinstance(local, SignedStructureLearner):
        out["structure"] = local.structure().clone()
    return out


def spread(values: list[float]) -> str:
    """``median [min, max]`` of one number per master seed."""
    return f"{statistics.median(values):.1f} [{min(values):.1f}, {max(values):.1f}]"


def table(results: dict, first: int, last: int) -> list[str]:
    """One line per method: the medians [ranges] over the master seeds."""
    heads = (
        f"items, first {first}",
        f"taken %, first {first}",
        f"collisions, first {first}",
        f"steps/episode, last {last}",
    )
    lines = [f"{'method':<22}" + "".join(f"{head:>26}" for head in heads)]
    for method, result in results.items():
        items = result["items"][:, :first].sum(dim=1).float()
        offered = result["offered"][:, :first].sum(dim=1).float()
        taken = (100 * items / offered.clamp(min=1)).tolist()
        collisions = result["collisions"][:, :first].sum(dim=1).float().tolist()
        steps = result["steps"][:, -last:].float().mean(dim=1).tolist()
        columns = (items.tolist(), taken, collisions, steps)
        lines.append(f"{method:<22}" + "".join(f"{spread(c):>26}" for c in columns))
    return lines


def figure(results: dict, path: str) -> None:
    """The share of sensed items taken and the steps per episode: the median over the master
    seeds and its range."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, axes = plt.subplots(1, 2, figsize=(8, 3), dpi=80)
    for method, result in results.items():
        offered = result["offered"].float().numpy()  # [S, episodes]
        with np.errstate(invalid="ignore", divide="ignore"):  # an episode that saw no item
            taken = np.where(offered > 0, 100 * result["items"].numpy() / offered, np.nan)
        panels = (taken, result["steps"].float().numpy())
        for index, (axis, values) in enumerate(zip(axes, panels, strict=True)):
            if index == 0 and method not in METHODS:
                axis.plot([], [])  # no items to take: keep the colours of the other panel
                continue
            episode = np.arange(1, values.shape[1] + 1)
            (line,) = axis.plot(episode, np.nanmedian(values, axis=0), label=method)
            low, high = np.nanmin(values, axis=0), np.nanmax(values, axis=0)
            axis.fill_between(episode, low, high, alpha=0.15, color=line.get_color())
    axes[0].set(xlabel="episode", ylabel="sensed items taken (%)", title="what pays")
    axes[1].set(xlabel="episode", ylabel="steps to the goal", yscale="log", title="the task")
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=10, help="master seeds (one experiment each)")
    parser.add_argument("--episodes", type=int, default=40, help="episodes per experiment")
    parser.add_argument("--first", type=int, default=10, help="the first episodes counted")
    parser.add_argument("--last", type=int, default=10, help="the last episodes counted")
    parser.add_argument("--items", type=int, default=10, help="items drawn per episode")
    parser.add_argument("--period", type=int, default=0, help="obstacle period (0 static)")
    parser.add_argument("--figure", default=None, help="where to write the figure (PNG)")
    parser.add_argument(
        "--no-reference", action="store_true", help="skip the grid without items (faster)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    world = PayingGrid(PayingConfig(num_items=args.items))
    seeds = list(range(args.seeds))
    results = {}
    for method in METHODS:
        start = time.perf_counter()
        results[method] = run(method, world, seeds, args.episodes, args.period)
        print(f"# {method}: {time.perf_counter() - start:.1f} s")
    if not args.no_reference:  # the task alone: the grid with no items (what collecting costs)
        plain = PayingGrid(PayingConfig(num_items=0))
        results["factor-q, no items"] = run("factor-q", plain, seeds, args.episodes, args.period)
    print(
        f"# paying grid 10x10, 10 obstacles (period {args.period}), {args.items} items of +1; "
        f"{args.seeds} master seeds, {args.episodes} episodes: median [min, max] over seeds"
    )
    print("\n".join(table(results, args.first, args.last)))
    structure = results["factor-q-learned"]["structure"]
    right = (structure == world.dependency).all(dim=-1)  # [S, A]
    print(
        f"learned structure: {int(right.sum())} of {right.numel()} actuators exactly "
        f"{{proximity a, item a}}"
    )
    if args.figure:
        figure(results, args.figure)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
