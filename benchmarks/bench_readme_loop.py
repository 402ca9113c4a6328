"""Milliseconds per batched step of the torchrl path's README loop (issue 17, deliverable 2).

The loop: ``FactoredGridEnv`` in the dynamic world (10x10, 10 obstacles, scattered every step)
+ ``SplitLocalReward`` + ``TaskQTable(sparse_grad=True)`` / ``LocalRewardTable`` +
``FactorQPolicy`` + ``FactorQLoss``, driven by ``OnlineCollector``, on 1 torch thread. For each
``S`` it prints the best of ``--blocks`` blocks of ``--steps`` ``collector.step()`` calls, as wall
time and as process CPU time (steadier on a shared machine), the env steps per second, and the
minor page faults per step (memory the allocator gave back to the system and took again).

To compare two commits, run this file from a checkout of each, alternately, several times (the
A/B tables of docs/howto/speed.md and of the closing notes were made that way):

    .venv/bin/python benchmarks/bench_readme_loop.py --sizes 1024 4096

Timings are never asserted anywhere; not a package on purpose (the torchrl wheel installs a
top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import time

try:
    import resource  # Unix: minor page faults per step, one cost of large temporaries
except ImportError:  # pragma: no cover - Windows
    resource = None

import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv

from factorq_envs import FactoredGridEnv, SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss
from factorq_torch.policy import FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable


def _faults() -> int:
    return 0 if resource is None else resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def best_step(count: int, blocks: int, steps: int) -> tuple[float, float, float]:
    """(wall, CPU) seconds per batched step of ``count`` experiments, the best block of each,
    and the minor page faults per step of the block with the best wall time."""
    base = FactoredGridEnv(
        size=10, num_obstacles=10, obstacle_period=1, batch_size=(count,), seed=0
    )
    env = TransformedEnv(base, SplitLocalReward())
    task = TaskQTable(count, 100, sparse_grad=True)
    local = LocalRewardTable(count)
    policy = TensorDictSequential(task, local, FactorQPolicy(count, seed=0))
    collector = OnlineCollector(env, policy, FactorQLoss(task, local), runs=10, episodes=200)
    for _ in range(5):  # warm-up
        collector.step()
    wall = cpu = float("inf")
    faults = 0.0
    for _ in range(blocks):
        wall_start, cpu_start, faults_start = time.perf_counter(), time.process_time(), _faults()
        for _ in range(steps):
            collector.step()
        block_wall = (time.perf_counter() - wall_start) / steps
        if block_wall < wall:
            wall, faults = block_wall, (_faults() - faults_start) / steps
        cpu = min(cpu, (time.process_time() - cpu_start) / steps)
    return wall, cpu, faults


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096])
    parser.add_argument("--blocks", type=int, default=5)
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(
        f"{'S':>6} {'wall ms/step':>13} {'CPU ms/step':>12} {'env steps/s (wall)':>19} "
        f"{'page faults/step':>17}"
    )
    for count in args.sizes:
        wall, cpu, faults = best_step(count, args.blocks, args.steps)
        print(
            f"{count:>6} {wall * 1e3:>13.3f} {cpu * 1e3:>12.3f} {count / wall / 1e6:>17.3f} M "
            f"{faults:>17.1f}"
        )


if __name__ == "__main__":
    main()
