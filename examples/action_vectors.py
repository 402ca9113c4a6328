"""Simultaneous actuators: Factor-Q acting on an action vector against flat Q over the joint
actions (issue 40, item 4; docs/tutorials/action-vectors.md).

The body is ``factorq_envs.vector_grid``'s: a horizontal and a vertical drive of three values
each, firing together (nine joint actions), one local reward per drive. Three methods, each on
``--seeds`` independent experiments of ``--episodes`` episodes (fresh tables, one run):

- ``vector-factor-q``: ``factorq_torch.vector.VectorFactorQ`` on the vector: task Q over the
  cell and the joint action, a local table per drive value keyed by its own sensor, each drive's
  local reward kept separate, eqs. 2-3 per drive;
- ``flat-factor-q``: the paper's Factor-Q over the nine joint actions as nine actions: a local
  table per joint action keyed by both of its sensors, fed the *summed* local reward;
- ``flat-q-learning``: Q-learning over the nine joint actions on cell x sensor pattern (1,600
  states), the conventional reward.

It prints, per world and method, the means per experiment of total steps (the paper's learning
speed), episodes to a path of ``THRESHOLD`` steps (the first episode from which ten episodes
average at most that), the mean path of the last 20 episodes, collisions (drive bumps) and
greedy collisions, for each of ``--master-seeds`` master seeds (disjoint random streams), then
the ratios against ``vector-factor-q`` (median and range over the master seeds), and writes the
figure.

    python examples/action_vectors.py --out action_vectors.png
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from factorq_envs.vector_grid import (
    NVEC,
    VectorGridConfig,
    drive_dependency,
    initial_vector_state,
    reset_vector_worlds,
    step_vector_worlds,
    vector_layout,
    vector_sensors,
)
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.functional import qlearning_state
from factorq_torch.vector import NeuralVectorFactorQ, VectorFactorQ

METHODS = ("vector-factor-q", "flat-factor-q", "flat-q-learning")
#: Run on demand (``--methods``): the task values from a network (``NeuralVectorFactorQ``).
NEURAL = "neural-vector-factor-q"
WORLDS = {"static": 0, "dynamic": 1}
#: Ten episodes averaging at most this many steps count as learned (4x the static layout's
#: shortest path of 10 steps; the empty grid's is 9).
THRESHOLD = 40
WINDOW = 10
#: "final steps": the mean path length of the last this many episodes.
FINAL = 20


def joint_dependency() -> torch.Tensor:
    """Flat Factor-Q's parents: joint action ``(h, v)`` reads both of its drives' sensors,
    ``[9, 4]`` bool (``joint_action_index`` order)."""
    per_value = drive_dependency()  # [6, 4]
    rows = [per_value[h] | per_value[3 + v] for h in range(NVEC[0]) for v in range(NVEC[1])]
    return torch.stack(rows)


def make_agent(method: str, seeds: int, config: VectorGridConfig, seed: int) -> VectorFactorQ:
    """The agent of ``method`` for ``seeds`` experiments."""
    joint = NVEC[0] * NVEC[1]
    if method == "vector-factor-q":
        return VectorFactorQ(seeds, config.num_cells, NVEC, drive_dependency(), seed=seed)
    if method == NEURAL:
        return NeuralVectorFactorQ(seeds, config.num_cells, NVEC, drive_dependency(), seed=seed)
    if method == "flat-factor-q":
        return VectorFactorQ(seeds, config.num_cells, (joint,), joint_dependency(), seed=seed)
    if method == "flat-q-learning":
        states = config.num_cells * 2**config.num_sensors
        return VectorFactorQ(seeds, states, (joint,), None, seed=seed, local=False)
    raise ValueError(f"method={method!r} is unknown: choose one of {', '.join((*METHODS, NEURAL))}")


def run(
    method: str,
    *,
    seeds: int = 20,
    episodes: int = 200,
    master_seed: int = 0,
    config: VectorGridConfig | None = None,
) -> dict[str, torch.Tensor]:
    """``seeds`` experiments of ``episodes`` episodes of ``method``: per-episode ``steps``,
    ``collisions`` (drive bumps) and ``greedy_collisions`` (on non-exploratory steps), each
    ``[seeds, episodes]``.

    >>> out = run("vector-factor-q", seeds=2, episodes=3, config=VectorGridConfig(size=4,
    ...           num_obstacles=2))
    >>> sorted(out), tuple(out["steps"].shape)
    (['collisions', 'greedy_collisions', 'steps'], (2, 3))
    """
    config = config or VectorGridConfig()
    agent = make_agent(method, seeds, config, master_seed)
    key = derive_keys(master_seed, STREAM_WORLD, seeds)
    layout = vector_layout(config) if config.obstacle_period == 0 else None
    everyone = torch.ones(seeds, dtype=torch.bool)
    state = reset_vector_worlds(initial_vector_state(seeds, config), everyone, key, config, layout)
    metrics = {name: torch.zeros(seeds, episodes) for name in ("steps", "collisions", "greedy")}
    episode = torch.zeros(seeds, dtype=torch.int64)
    collisions = torch.zeros(seeds)
    greedy = torch.zeros(seeds)
    rows = torch.arange(seeds)
    flat = method not in ("vector-factor-q", NEURAL)
    while bool((episode < episodes).any()):
        sensors = vector_sensors(state, config)
        task_state = qlearning_state(state.cell, sensors) if not agent.local else state.cell
        action, exploratory = agent.act(task_state, sensors)
        joint = action[:, 0] if flat else None
        drives = torch.stack((joint // NVEC[1], joint % NVEC[1]), 1) if flat else action
        new, outcome = step_vector_worlds(state, drives, key, config)
        next_sensors = vector_sensors(new, config)
        if agent.local:
            local = outcome.collision.sum(1, keepdim=True) if flat else outcome.collision
            agent.update(
                state.cell, sensors, action, outcome.task_reward, local,
                new.cell, next_sensors, outcome.terminated,
            )  # fmt: skip
        else:
            agent.update(
                task_state, sensors, action, outcome.reward, None,
                qlearning_state(new.cell, next_sensors), next_sensors, outcome.terminated,
            )  # fmt: skip
        bumps = (outcome.collision < 0).sum(1).to(torch.float32)  # [S]
        collisions += bumps
        greedy += bumps * ~exploratory
        done = outcome.terminated | outcome.truncated
        recording = done & (episode < episodes)
        index = episode.clamp(max=episodes - 1)
        for name, value in (
            ("steps", new.episode_step.to(torch.float32)),
            ("collisions", collisions),
            ("greedy", greedy),
        ):
            metrics[name][rows, index] = torch.where(recording, value, metrics[name][rows, index])
        collisions = collisions.masked_fill(done, 0.0)
        greedy = greedy.masked_fill(done, 0.0)
        episode = episode + done
        state = reset_vector_worlds(new, done, key, config, layout) if bool(done.any()) else new
    return {
        "steps": metrics["steps"],
        "collisions": metrics["collisions"],
        "greedy_collisions": metrics["greedy"],
    }


def episodes_to_threshold(steps: torch.Tensor, threshold: float = THRESHOLD) -> torch.Tensor:
    """Per experiment, the first episode from which ``WINDOW`` episodes average at most
    ``threshold`` steps (``[S, E] -> [S]`` float; ``E`` where it never does).

    >>> episodes_to_threshold(torch.tensor([[50.0] * 3 + [10.0] * 12]), 20.0)
    tensor([3.])
    """
    windows = steps.unfold(1, WINDOW, 1).mean(-1)  # [S, E - WINDOW + 1]
    reached = windows <= threshold
    first = torch.where(reached.any(1), reached.to(torch.int8).argmax(1), steps.shape[1])
    return first.to(torch.float32)


def summary(out: dict[str, torch.Tensor]) -> dict[str, float]:
    """Means per experiment: total steps, episodes to the threshold, the mean path of the last
    ``FINAL`` episodes, collisions, greedy collisions."""
    return {
        "total steps": float(out["steps"].sum(1).mean()),
        "episodes to threshold": float(episodes_to_threshold(out["steps"]).mean()),
        "final steps": float(out["steps"][:, -FINAL:].mean()),
        "collisions": float(out["collisions"].sum(1).mean()),
        "greedy collisions": float(out["greedy_collisions"].sum(1).mean()),
    }


def figure(
    curves: dict[tuple[str, str], torch.Tensor],
    path: str,
    episodes: int,
    worlds: dict[str, int],
    methods: tuple[str, ...],
) -> None:
    """Steps per episode and cumulative collisions, per world, for each method."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(worlds), figsize=(8, 5.2), sharex=True, squeeze=False)
    colours = {
        "vector-factor-q": "C0",
        "flat-factor-q": "C2",
        "flat-q-learning": "C3",
        NEURAL: "C1",
    }
    for column, world in enumerate(worlds):
        for method in methods:
            steps, collisions = curves[(world, method)]
            x = range(1, episodes + 1)
            axes[0, column].plot(x, steps, color=colours[method], label=method, lw=1)
            axes[1, column].plot(x, collisions.cumsum(0), color=colours[method], lw=1)
        axes[0, column].set_yscale("log")
        axes[0, column].set_title(f"{world} world")
        axes[1, column].set_xlabel("episode")
    axes[0, 0].set_ylabel("steps per episode")
    axes[1, 0].set_ylabel("cumulative collisions")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Two drives x three values: Factor-Q on the vector vs flat Q (mean over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--master-seeds", type=int, default=5)
    parser.add_argument("--seeds", type=int, default=20, help="experiments per master seed")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--out", default="action_vectors.png", help="the figure")
    parser.add_argument(
        "--methods",
        default=",".join(METHODS),
        help=f"comma-separated, the first is the reference of the ratios ({NEURAL} on demand)",
    )
    parser.add_argument(
        "--regimes", default=",".join(WORLDS), help="obstacle regimes, comma-separated"
    )
    args = parser.parse_args(argv)
    methods = tuple(args.methods.split(","))
    worlds = {name: WORLDS[name] for name in args.regimes.split(",")}
    torch.set_num_threads(1)
    results: dict[tuple[str, str], list[dict[str, float]]] = {}
    curves: dict[tuple[str, str], list[torch.Tensor]] = {}
    for world, period in worlds.items():
        config = VectorGridConfig(obstacle_period=period)
        for method in methods:
            for master in range(args.master_seeds):
                start = time.perf_counter()
                out = run(
                    method,
                    seeds=args.seeds,
                    episodes=args.episodes,
                    master_seed=master,
                    config=config,
                )
                row = summary(out)
                results.setdefault((world, method), []).append(row)
                curves.setdefault((world, method), []).append(
                    torch.stack((out["steps"].mean(0), out["collisions"].mean(0)))
                )
                cells = "  ".join(f"{name} {value:9.1f}" for name, value in row.items())
                print(
                    f"{world:8} {method:16} master seed {master}: {cells}  "
                    f"({time.perf_counter() - start:.1f} s)",
                    flush=True,
                )
    print()
    print(f"ratio to {methods[0]}: median [range] over the master seeds")
    for world in worlds:
        base = results[(world, methods[0])]
        for method in methods[1:]:
            parts = []
            for name in base[0]:
                ratios = [
                    other[name] / max(mine[name], 1e-9)
                    for other, mine in zip(results[(world, method)], base, strict=True)
                ]
                parts.append(
                    f"{name} {statistics.median(ratios):.2f}x [{min(ratios):.2f}-{max(ratios):.2f}]"
                )
            print(f"{world:8} {method:16} / {methods[0]}: " + "; ".join(parts))
    mean_curves = {
        key: torch.stack(value).mean(0) for key, value in curves.items()
    }  # [2, E] per (world, method)
    figure(mean_curves, args.out, args.episodes, worlds, methods)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
