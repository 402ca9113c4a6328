"""Factor-Q's risk options measured over master seeds (issue 39, ``docs/decisions.md``).

``--stall``: the heading body with sensor noise (``factorq dependencies``' custom setting, its
defaults: static 6x6 grid, 4 obstacles, 10 runs x 1 episode, 1,000 steps at most), Factor-Q with
the oracle and with the learned structure, paper eqs. 2-3 against the risk gate
(``AgentConfig.risk_gate``), and Q-learning: steps per episode and the share of episodes
truncated, per master seed (each the mean of ``--seeds`` experiments), then the median and range
over the master seeds.

``--exploration``: tabular Factor-Q with the oracle dependency, uniform against risk-aware
exploration (``AgentConfig.exploration``), and Q-learning, on the paper's grid (``--regime``,
``factorq paper``'s defaults but ``--runs`` runs) and on declared third-party envs
(``--steps`` env steps per experiment, ``--cliff-seeds`` experiments): Gymnasium's CliffWalking
and FrozenLake 8x8 declared as in ``docs/tutorials/own-env.md``, MiniGrid's ``LavaGapS6`` as in
``docs/tutorials/declared-envs.md``. Collisions (falls) and the task measure (grid: steps per
episode, every episode reaching the goal; the others: goals reached per experiment) per master
seed, the median and range over them (``docs/tutorials/risk-options.md`` holds the tables).

    .venv/bin/python benchmarks/bench_risk_options.py --stall --masters 5 --seeds 48
    .venv/bin/python benchmarks/bench_risk_options.py --exploration --masters 5 --seeds 20
    .venv/bin/python benchmarks/bench_risk_options.py --exploration --worlds cliff,lake,lava \
        --masters 5 --cliff-seeds 10 --steps 1000

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch


def _spread(values: list[float]) -> str:
    return f"{statistics.median(values):.1f} [{min(values):.1f}-{max(values):.1f}]"


def stall(masters: list[int], seeds: int, noises: list[float]) -> None:
    from factorq_trainers.commands.dependencies import command as dependencies

    rows: dict[tuple[float, str], dict[str, list[float]]] = {}
    for noise in noises:
        for master in masters:
            for gate in ("off", "on"):
                config = dependencies.DependenciesConfig(
                    body="heading",
                    sensors="cross",
                    sensor_noise=noise,
                    seeds=seeds,
                    seed=master,
                    risk_gate=gate,
                    methods=("factor-q-learned", "factor-q")
                    if gate == "on"
                    else dependencies.METHODS[:4],
                    threads=1,
                    out="unused",
                )
                summary = dependencies.run_unit(config, dependencies.units(config)[0])
                for method, entry in summary["summary"]["methods"].items():
                    if method == "factor-q-joint":
                        continue
                    name = method if method == "q-learning" else f"{method}, gate {gate}"
                    row = rows.setdefault((noise, name), {"steps": [], "truncated": []})
                    row["steps"].append(entry["steps_per_episode"])
                    row["truncated"].append(100 * entry["fraction_truncated"])
                    row.setdefault("collisions", []).append(entry["collisions_per_experiment"])
    print(f"master seeds {masters}, {seeds} experiments each; median [range] over master seeds")
    print("| sensor noise | method | steps per episode | episodes truncated (%) | collisions |")
    print("| ---: | --- | ---: | ---: | ---: |")
    for (noise, name), row in rows.items():
        print(
            f"| {noise} | {name} | {_spread(row['steps'])} | {_spread(row['truncated'])} | "
            f"{_spread(row['collisions'])} |"
        )
    for (noise, name), row in rows.items():
        print(noise, name, "per master:", [round(v, 1) for v in row["steps"]])


def _declared_falls(make, exploration, master, seeds, steps, penalty) -> tuple:
    """Falls and goals of ``seeds`` experiments of ``steps`` env steps on the declared env
    ``make(seed)``: Factor-Q with the oracle and ``exploration``, or Q-learning for None (its
    state the cell, the heading and every sensor, as in the paper); a goal is an episode that
    ends without a collision. "Risky": a fall more likely than not, half of the fall's
    ``penalty``."""
    from factorq_envs.declared_env import declared_torchrl_env
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, derive_keys
    from factorq_torch.collectors import OnlineCollector
    from factorq_torch.tables import LocalRewardTable, TaskQTable
    from factorq_trainers.methods.experiment import online_agent

    base = declared_torchrl_env(make, seeds=[master * 1000 + index for index in range(seeds)])
    config = base.config
    task = TaskQTable(
        seeds,
        config.num_cells,
        with_sensors=exploration is None,
        num_sensors=config.num_sensors,
        num_headings=config.num_headings,
        num_actions=config.num_actuators,
    )
    local, agent = None, AgentConfig()
    if exploration is not None:
        local = LocalRewardTable(seeds, dependency=base.dependency)
        agent = AgentConfig(exploration=exploration, risk_threshold=penalty / 2)
    keys = derive_keys(master, STREAM_POLICY, seeds)
    collector = OnlineCollector(
        *online_agent(base, task, local, agent, keys), runs=1, episodes=10**6
    )
    falls = goals = 0
    for step, td in enumerate(collector, start=1):
        bump = td["next", "bump"].any(-1)
        falls += int(bump.sum())
        goals += int((td["next", "terminated"].squeeze(-1) & ~bump).sum())
        if step == steps:
            break
    return falls / seeds, goals / seeds


def _cliff_falls(exploration: str | None, master: int, seeds: int, steps: int) -> tuple:
    """CliffWalking as ``docs/tutorials/own-env.md`` declares it: one sensor per move (the
    cliff that way), a fall the collision (-100); the cell is the env's state."""
    import gymnasium

    from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv

    moves = ((-1, 0), (0, 1), (1, 0), (0, -1))  # up, right, down, left

    def cliff_ahead(step):
        row, col = divmod(int(step.observation), 12)
        return np.array([row + dr == 3 and 0 < col + dc < 11 for dr, dc in moves])

    cliff = Declaration(
        num_sensors=4,
        sensors=cliff_ahead,
        collision=lambda step: step.reward == -100,
        penalty=100.0,
        actuator_names=("up", "right", "down", "left"),
        task_state=lambda step: int(step.observation),
        num_cells=48,
        dependency=tuple(tuple(a == k for k in range(4)) for a in range(4)),
    )
    return _declared_falls(
        lambda seed: FactorQEnv(gymnasium.make("CliffWalking-v1"), cliff, seed=seed),
        exploration,
        master,
        seeds,
        steps,
        100.0,
    )


def _lake_falls(exploration: str | None, master: int, seeds: int, steps: int) -> tuple:
    """FrozenLake 8x8 (not slippery), declared as ``docs/tutorials/own-env.md`` declares the
    lake: one sensor per move (a hole that way), a fall the collision (terminated, reward 0)."""
    import gymnasium

    from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv

    lake = gymnasium.make("FrozenLake-v1", map_name="8x8", is_slippery=False)
    desc = ["".join(c.decode() for c in row) for row in lake.unwrapped.desc.tolist()]
    moves = ((0, -1), (1, 0), (0, 1), (-1, 0))  # left, down, right, up

    def hole(row: int, col: int) -> bool:
        return 0 <= row < 8 and 0 <= col < 8 and desc[row][col] == "H"

    declaration = Declaration(
        num_sensors=4,
        sensors=lambda step: np.array(
            [
                hole(int(step.observation) // 8 + dr, int(step.observation) % 8 + dc)
                for dr, dc in moves
            ]
        ),
        collision=lambda step: step.terminated and step.reward == 0,
        task_reward=lambda step: step.reward,  # a hole costs the task nothing
        actuator_names=("left", "down", "right", "up"),
        task_state=lambda step: int(step.observation),
        num_cells=64,
        dependency=tuple(tuple(a == k for k in range(4)) for a in range(4)),
    )
    return _declared_falls(
        lambda seed: FactorQEnv(
            gymnasium.make("FrozenLake-v1", map_name="8x8", is_slippery=False),
            declaration,
            seed=seed,
        ),
        exploration,
        master,
        seeds,
        steps,
        1.0,
    )


LAVA_ENV = "MiniGrid-LavaGapS6-v0"


def _lava_falls(exploration: str | None, master: int, seeds: int, steps: int) -> tuple:
    """MiniGrid's lava (``LAVA_ENV``: the gap moves every episode) with the body of
    ``factorq minigrid`` (``minigrid_adapter.declaration``: forward, left, right; the view's cells
    ahead, left and right; the cell and heading the task state), its sensors reading lava and a
    fall the collision, as ``docs/tutorials/declared-envs.md`` declares it."""
    import dataclasses

    import gymnasium
    from minigrid.core.constants import OBJECT_TO_IDX

    from factorq_envs import minigrid_adapter
    from factorq_envs.gymnasium_adapter import FactorQEnv

    minigrid_adapter.require_minigrid()  # registers the envs
    cells = np.array(minigrid_adapter.view_cells(minigrid_adapter.check_layout("front3")))
    lava = dataclasses.replace(
        minigrid_adapter.declaration(gymnasium.make(LAVA_ENV).unwrapped.width),
        sensors=lambda step: (
            step.observation["image"][cells[:, 0], cells[:, 1], 0] == OBJECT_TO_IDX["lava"]
        ),
        collision=lambda step: step.terminated and step.reward == 0,  # lava, not the goal
        task_reward=lambda step: step.reward,
    )
    return _declared_falls(
        lambda seed: FactorQEnv(gymnasium.make(LAVA_ENV), lava, seed=seed),
        exploration,
        master,
        seeds,
        steps,
        1.0,
    )


def _grid(exploration: str | None, master: int, seeds: int, runs: int, regime: str) -> tuple:
    """The paper's grid in ``regime`` (``factorq paper``'s defaults, ``runs`` runs): collisions per
    run and steps per episode."""
    from factorq_envs.regimes import REGIME_PERIODS
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
    from factorq_trainers.compiled import fast
    from factorq_trainers.methods.experiment import check_world_options

    world = check_world_options(10, 10, 10_000, 0, (regime,))
    periods = torch.full((seeds,), REGIME_PERIODS[regime], dtype=torch.int64)
    algorithm = "q-learning" if exploration is None else "factor-q"
    agent = AgentConfig() if exploration is None else AgentConfig(exploration=exploration)
    metrics = fast.run_experiments(
        algorithm,
        periods,
        world,
        agent,
        runs,
        200,
        derive_keys(master, STREAM_WORLD, seeds),
        derive_keys(master, STREAM_POLICY, seeds),
        threads=1,
    )
    steps = metrics["steps"].double()
    # every episode reaches the goal within 10,000 steps: the task measure is its length
    return float(metrics["collisions"].double().sum(dim=(1, 2)).mean()) / runs, float(steps.mean())


def exploration(
    masters: list[int], seeds: int, steps: int, runs: int, worlds: list[str], regime: str
) -> None:
    methods = {
        "Factor-Q, uniform": "uniform",
        "Factor-Q, risk-aware": "risk-aware",
        "Q-learning": None,
    }
    names = {
        "grid": f"grid ({regime})",
        "cliff": "CliffWalking",
        "lake": "FrozenLake 8x8",
        "lava": LAVA_ENV,
    }
    declared = {"cliff": _cliff_falls, "lake": _lake_falls, "lava": _lava_falls}
    for measure in worlds:
        world = names[measure]
        results: dict[str, dict[str, list[float]]] = {}
        for master in masters:
            for name, kind in methods.items():
                started = time.perf_counter()
                if measure == "grid":
                    collisions, success = _grid(kind, master, seeds, runs, regime)
                else:
                    collisions, success = declared[measure](kind, master, seeds, steps)
                entry = results.setdefault(name, {"collisions": [], "success": []})
                entry["collisions"].append(collisions)
                entry["success"].append(success)
                print(
                    f"  {world} master {master} {name}: {collisions:.2f} collisions, success "
                    f"{success:.3f} ({time.perf_counter() - started:.0f} s)",
                    flush=True,
                )
        q = results["Q-learning"]["collisions"]
        print(f"\n{world}: median [range] over master seeds {masters}")
        task = "steps per episode" if measure == "grid" else "goals reached per experiment"
        print(f"| method | collisions | {task} | Q-learning / method, collisions |")
        print("| --- | ---: | ---: | ---: |")
        for name, entry in results.items():
            ratios = [
                a / b if b else float("inf") for a, b in zip(q, entry["collisions"], strict=True)
            ]
            print(
                f"| {name} | {_spread(entry['collisions'])} | {_spread(entry['success'])} | "
                f"{_spread(ratios)} |"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--stall", action="store_true")
    parser.add_argument("--exploration", action="store_true")
    parser.add_argument("--masters", type=int, default=5, help="master seeds 0 .. N-1")
    parser.add_argument("--seeds", type=int, default=48, help="experiments per master seed")
    parser.add_argument("--noises", default="0,0.01,0.05,0.1")
    parser.add_argument("--steps", type=int, default=1000, help="env steps of a declared env")
    parser.add_argument(
        "--worlds", default="grid,cliff", help="grid, cliff, lake, lava (comma-separated)"
    )
    parser.add_argument("--regime", default="dynamic", help="the grid's obstacle regime")
    parser.add_argument("--cliff-seeds", type=int, default=10, help="experiments on a declared env")
    parser.add_argument("--runs", type=int, default=10, help="grid runs of 200 episodes")
    args = parser.parse_args()
    torch.set_num_threads(1)
    masters = list(range(args.masters))
    if args.stall:
        stall(masters, args.seeds, [float(n) for n in args.noises.split(",")])
    if args.exploration:
        worlds = args.worlds.split(",")
        for world in worlds:
            seeds = args.seeds if world == "grid" else args.cliff_seeds
            exploration(masters, seeds, args.steps, args.runs, [world], args.regime)


if __name__ == "__main__":
    main()
