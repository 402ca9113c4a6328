"""Arbitration in the strike world: plain Factor-Q, Factor-Q with arbitration and Q-learning.

The world (``factorq_envs.strike``): a 5 x 5 grid whose goal room opens only when the body
strikes its door (a collision, local reward -1); the goal pays 100. Each method trains
``--experiments`` experiments for each of ``--seeds`` master seeds (``--episodes`` episodes,
one run, the paper's epsilon, gamma and alpha), then acts greedily for one episode of at most
``--greedy-steps`` steps. Printed per method, over all experiments:

- solved: the share of experiments whose greedy episode reaches the goal;
- greedy steps: the greedy episode's length where it does (the shortest path is 9 steps, the
  strike included);
- training steps per episode, the share of training episodes that reached the goal;
- collisions outside the required strike, per training episode, per 1,000 training steps and
  in the greedy episode: every collision but the one that opens the door (at most one per
  episode).

The figure (``--figure``) shows the training episodes' lengths and the collisions outside the
strike per episode, averaged over the experiments, and the solved shares.

Run: ``.venv/bin/python examples/arbitration.py [--seeds 5 --experiments 20 --episodes 100]
[--figure docs/arbitration.png]`` (about 4 minutes on one core here, most of it plain Factor-Q,
whose episodes mostly run to the 1,000-step limit).
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from factorq_envs.strike import StrikeConfig, StrikeWorld
from factorq_envs.torchrl_env import FactoredGridEnv
from factorq_envs.transforms import SplitLocalReward
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, derive_keys
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable

METHODS = ("factor-q", "factor-q + arbitration", "q-learning")


def agent(method: str, world: StrikeWorld, count: int, keys: torch.Tensor) -> tuple:
    """``(env, policy, loss)`` of ``method`` for ``count`` experiments (policy stream keys
    ``keys``), the paper's learning parameters."""
    config, paper = world.config, AgentConfig()
    base = FactoredGridEnv(world=world, batch_size=(count,))
    if method == "q-learning":
        task = TaskQTable(count, config.num_cells, with_sensors=True, num_sensors=4)
        policy = EpsilonGreedyPolicy(count, keys=keys, epsilon=paper.epsilon)
        return base, TensorDictSequential(task, policy), TabularQLoss(task)
    arbitration = method == "factor-q + arbitration"
    task = TaskQTable(count, config.num_cells)
    local = LocalRewardTable(count, dependency=world.dependency)
    policy = FactorQPolicy(count, keys=keys, epsilon=paper.epsilon, arbitration=arbitration)
    loss = FactorQLoss(task, local, gamma=paper.gamma, alpha=paper.alpha, arbitration=arbitration)
    env = TransformedEnv(base, SplitLocalReward())
    return env, TensorDictSequential(task, local, policy), loss


def train(method: str, world: StrikeWorld, seeds: int, experiments: int, episodes: int) -> dict:
    """Train every experiment of ``method``; per experiment and episode: steps, whether the
    goal was reached, collisions outside the strike. Then one greedy episode each."""
    count = seeds * experiments
    keys = torch.cat([derive_keys(seed, STREAM_POLICY, experiments) for seed in range(seeds)])
    env, policy, loss = agent(method, world, count, keys)
    collector = OnlineCollector(env, policy, loss, runs=1, episodes=episodes)
    strikes = torch.zeros(count, episodes)
    reached = torch.zeros(count, episodes)
    rows = torch.arange(count)
    for td in collector:
        episode = td["collector", "episode"]
        opened = td["next", "door_open"][:, 0] & ~td["door_open"][:, 0]
        strikes[rows, episode] += opened.float()
        reached[rows, episode] += td["next", "terminated"][:, 0].float()
    metrics = collector.metrics
    steps = metrics["steps"][:, 0].float()
    outside = metrics["collisions"][:, 0].float() - strikes
    return {
        "steps": steps,
        "reached": reached.clamp(max=1),
        "outside": outside,
        **greedy(env, policy, count),
    }


def greedy(env, policy, count: int, limit: int = 100) -> dict:
    """One greedy episode per experiment (no learning): solved, its length, collisions outside
    the strike."""
    td = env.reset()
    done = torch.zeros(count, dtype=torch.bool)
    length, outside = torch.zeros(count), torch.zeros(count)
    with set_exploration_type(ExplorationType.DETERMINISTIC), torch.no_grad():
        for _ in range(limit):
            td = env.step(policy(td))
            live = ~done
            opened = td["next", "door_open"][:, 0] & ~td["door_open"][:, 0]
            bumped = td["next", "bump"].any(-1)
            length += live.float()
            outside += (bumped & ~opened & live).float()
            done = done | td["next", "terminated"][:, 0]
            td = env.step_mdp(td)
            if bool(done.all()):
                break
    return {"solved": done.float(), "greedy_steps": length, "greedy_outside": outside}


def table(results: dict) -> str:
    """The printed table, one line per method."""
    lines = [
        "| method | solved | greedy steps | training steps / episode | episodes reaching "
        "the goal | collisions outside the strike / training episode | ... / 1,000 training "
        "steps | greedy collisions outside the strike |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, r in results.items():
        solved = r["solved"].bool()
        steps = f"{r['greedy_steps'][solved].mean():.1f}" if solved.any() else "-"
        lines.append(
            f"| {method} | {solved.float().mean():.1%} ({int(solved.sum())}/{len(solved)}) | "
            f"{steps} | {r['steps'].mean():.0f} | {r['reached'].mean():.1%} | "
            f"{r['outside'].mean():.2f} | {1000 * r['outside'].sum() / r['steps'].sum():.2f} | "
            f"{r['greedy_outside'].mean():.2f} |"
        )
    return "\n".join(lines)


def per_master(results: dict, seeds: int) -> str:
    """Per master seed (its ``experiments`` experiments): the solved share and the collisions
    outside the strike per training episode, then the median and range over the master seeds."""
    lines = [
        "| method | solved, per master seed | median [range] | collisions outside the strike "
        "/ training episode, per master seed | median [range] |",
        "| --- | --- | ---: | --- | ---: |",
    ]
    for method, r in results.items():
        solved = r["solved"].reshape(seeds, -1).mean(1)
        outside = r["outside"].reshape(seeds, -1, r["outside"].shape[1]).mean((1, 2))
        cells = []
        for values, form in ((solved, "{:.0%}"), (outside, "{:.2f}")):
            median = values.median().item()  # (the lower median for an even count)
            cells.append(", ".join(form.format(v) for v in values.tolist()))
            cells.append(
                f"{form.format(median)} [{form.format(values.min())}-{form.format(values.max())}]"
            )
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def figure(results: dict, path: str) -> None:
    """Episode lengths and collisions outside the strike per training episode (means over the
    experiments), and the solved shares."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(11, 3.4), gridspec_kw={"width_ratios": [2, 2, 1.2]})
    colours = {METHODS[0]: "tab:blue", METHODS[1]: "tab:green", METHODS[2]: "tab:red"}
    for method, r in results.items():
        episodes = torch.arange(1, r["steps"].shape[1] + 1)
        axes[0].plot(episodes, r["steps"].mean(0), label=method, color=colours[method])
        axes[1].plot(episodes, r["outside"].mean(0), label=method, color=colours[method])
    axes[0].set(xlabel="training episode", ylabel="steps", yscale="log", title="episode length")
    axes[1].set(
        xlabel="training episode",
        ylabel="collisions",
        yscale="symlog",
        title="collisions outside the strike",
    )
    axes[0].legend(fontsize=8)
    names = list(results)
    shares = [float(results[m]["solved"].mean()) for m in names]
    axes[2].bar(range(len(names)), shares, color=[colours[m] for m in names])
    labels = {METHODS[0]: "Factor-Q", METHODS[1]: "+ arbitration", METHODS[2]: "Q-learning"}
    axes[2].set_xticks(range(len(names)), [labels[m] for m in names], fontsize=8, rotation=20)
    axes[2].set(ylim=(0, 1.05), title="greedy episode solved")
    fig.suptitle("Strike world (5 x 5, the door opens only when struck, goal 100)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=5, help="master seeds")
    parser.add_argument("--experiments", type=int, default=20, help="experiments per seed")
    parser.add_argument("--episodes", type=int, default=100, help="training episodes")
    parser.add_argument("--size", type=int, default=5, help="side of the grid")
    parser.add_argument("--methods", default=",".join(METHODS), help="comma-separated")
    parser.add_argument("--figure", default=None, help="write the figure here (PNG)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    world = StrikeWorld(StrikeConfig(size=args.size))
    results = {}
    for method in args.methods.split(","):
        started = time.perf_counter()
        results[method] = train(method, world, args.seeds, args.experiments, args.episodes)
        print(f"{method}: {time.perf_counter() - started:.0f} s", flush=True)
    print(table(results))
    print(per_master(results, args.seeds))
    if args.figure:
        figure(results, args.figure)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
