"""Raw stepping speed of the FactoredGrid world with random actions.

Two paths over the same worlds:

- ``env.step``: ``FactoredGridEnv.step_and_maybe_reset``, the torchrl TensorDict path a collector
  drives (step, step_mdp, partial reset of finished worlds);
- ``functions``: the bare ``factorq_envs.grid_world`` functions a fused loop would call
  (``step_worlds``, the proximity observation, ``reset_worlds`` of finished worlds), no TensorDict.

Each at several batch sizes ``S`` (independent worlds), with ``torch.set_num_threads(1)`` and with
torch's default thread count. Figures are world-steps per second (``S`` x batched steps per
second). Run from the repository root:

    .venv/bin/python benchmarks/bench_env.py            # full table
    .venv/bin/python benchmarks/bench_env.py --sizes 1 4096 --seconds 0.5

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import time

import torch

from factorq_envs import FactoredGridEnv
from factorq_envs.grid_world import proximity, reset_worlds, step_worlds
from factorq_envs.regimes import REGIME_PERIODS


def random_actions(batch: int, steps: int) -> torch.Tensor:
    """Actions ``[steps, batch]`` from a private generator (drawn before the clock starts)."""
    generator = torch.Generator().manual_seed(0)
    return torch.randint(0, 4, (steps, batch), generator=generator)


def timed(step, seconds: float, warmup: int = 20) -> tuple[int, float]:
    """Call ``step(i)`` until ``seconds`` have passed; the calls made and the time they took."""
    for i in range(warmup):
        step(i)
    calls, start = 0, time.perf_counter()
    while True:
        for _ in range(50):
            step(calls)
            calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return calls, elapsed


def bench_env_step(batch: int, period: int, seconds: float) -> float:
    """Batched ``step_and_maybe_reset`` calls per second."""
    batch_size = () if batch == 1 else (batch,)
    env = FactoredGridEnv(obstacle_period=period, batch_size=batch_size, seed=0)
    actions = random_actions(batch, 4096).reshape(4096, *batch_size)
    state = {"td": env.reset()}

    def step(i: int) -> None:
        td = state["td"]
        td["action"] = actions[i % 4096]
        _, state["td"] = env.step_and_maybe_reset(td)

    calls, elapsed = timed(step, seconds)
    return calls / elapsed


def bench_functions(batch: int, period: int, seconds: float) -> float:
    """Batched calls per second of the bare world functions (step, observe, reset finished)."""
    env = FactoredGridEnv(obstacle_period=period, batch_size=(batch,), seed=0)
    env.reset()
    config, keys, periods, layout = env.config, env.world_keys, env.periods, env.static_obstacles
    actions = random_actions(batch, 4096)
    state = {"world": env.world_state}

    def step(i: int) -> None:
        world, outcome = step_worlds(state["world"], actions[i % 4096], keys, periods, config)
        proximity(world.cell, world.obstacles, config.size)  # the observation a policy reads
        finished = outcome.terminated | outcome.truncated
        state["world"] = reset_worlds(world, finished, keys, periods, layout, config)

    calls, elapsed = timed(step, seconds)
    return calls / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1, 64, 1024, 4096])
    parser.add_argument("--regimes", nargs="+", choices=sorted(REGIME_PERIODS), default=["dynamic"])
    parser.add_argument("--seconds", type=float, default=1.0, help="time per measurement")
    args = parser.parse_args()

    default_threads = torch.get_num_threads()
    print(f"torch {torch.__version__}, default threads {default_threads}")
    header = f"{'world':<13}{'path':<11}{'S':>6}{'threads':>9}{'batched steps/s':>17}"
    print(header + f"{'world-steps/s':>15}")
    print("-" * (len(header) + 15))
    for world in args.regimes:
        for path, bench in (("env.step", bench_env_step), ("functions", bench_functions)):
            for batch in args.sizes:
                for threads in sorted({1, default_threads}):
                    torch.set_num_threads(threads)
                    rate = bench(batch, REGIME_PERIODS[world], args.seconds)
                    print(
                        f"{world:<13}{path:<11}{batch:>6}{threads:>9}{rate:>17,.0f}"
                        f"{rate * batch:>15,.0f}",
                        flush=True,
                    )
    torch.set_num_threads(default_threads)


if __name__ == "__main__":
    main()
