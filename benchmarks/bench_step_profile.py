"""Where a step of the modular (torchrl) path goes: ATen calls, stage times, restarts, batch length.

For one algorithm's collector over the paper's mixed batch (worlds static / semi-dynamic /
dynamic, ``S`` experiments, 1 torch thread), after ``--skip`` plain steps (later in a run
episodes are short and nearly every step restarts some world); stage times are means over
``--steps`` steps, the restart comparison the best of alternating blocks after them, and the
calls are counted on a second collector at the same point (``--skip`` steps in):

1. CPU ms per step around each stage of ``OnlineCollector.step`` (policy, env step, learning,
   ``step_mdp``, bookkeeping, restart) and how many steps restarted a world;
2. CPU ms per step with the restarts given as ``reset(td, reset_mask=...)`` against the
   ``"_reset"`` entry, alternating blocks in one process;
3. ATen calls per step by the function of this project that made them (a ``TorchDispatchMode``
   counting every call that reaches the dispatcher), the largest first;
4. with ``--batched-steps``: the batched steps each algorithm's default paper batch needs (its
   slowest experiment's total steps) and their spread, from the fast path's metrics (the same
   numbers as the modular path's).

Examples (the figures of issue 17's closing note and ``docs/decisions.md``):

    .venv/bin/python benchmarks/bench_step_profile.py --algorithm q-learning --size 300
    .venv/bin/python benchmarks/bench_step_profile.py --algorithm q-learning --skip 8000
    .venv/bin/python benchmarks/bench_step_profile.py --batched-steps

Nothing is asserted; not a package on purpose (the torchrl wheel installs a top-level
``benchmarks``).
"""

from __future__ import annotations

import argparse
import collections
import sys
import time

import torch
from tensordict.nn import TensorDictSequential
from torch.utils._python_dispatch import TorchDispatchMode
from torchrl.envs import TransformedEnv

from factorq_envs import FactoredGridEnv, SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import MASK_KEY, EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable

PACKAGES = ("factorq_torch", "factorq_envs", "envs", "factorq_trainers", "trainers")


def build(algorithm: str, count: int) -> OnlineCollector:
    """A collector of ``count`` experiments, the three worlds in equal blocks (as the paper)."""
    periods = torch.tensor([0, 10, 1]).repeat_interleave(-(-count // 3))[:count]
    base = FactoredGridEnv(
        size=10, num_obstacles=10, obstacle_period=periods, batch_size=(count,), seed=0
    )
    if algorithm == "factor-q":
        env = TransformedEnv(base, SplitLocalReward())
        task, local = TaskQTable(count, 100, sparse_grad=True), LocalRewardTable(count)
        policy = TensorDictSequential(task, local, FactorQPolicy(count, seed=0))
        return OnlineCollector(env, policy, FactorQLoss(task, local), runs=10, episodes=200)
    task = TaskQTable(count, 100, with_sensors=True, sparse_grad=True)
    policy = TensorDictSequential(task, EpsilonGreedyPolicy(count, seed=0))
    return OnlineCollector(base, policy, TabularQLoss(task), runs=10, episodes=200)


class _Calls(TorchDispatchMode):
    """Counts ATen calls by the innermost function of this project on the Python stack."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        frame, where = sys._getframe(1), "other (torch, torchrl, tensordict)"
        while frame is not None:
            module = frame.f_globals.get("__name__", "")
            if module.split(".")[0] in PACKAGES:
                where = f"{module}.{frame.f_code.co_name}"
                break
            frame = frame.f_back
        self.calls[where] += 1
        return func(*args, **(kwargs or {}))


def count_calls(collector: OnlineCollector, steps: int, top: int) -> None:
    with _Calls() as mode:
        for _ in range(steps):
            collector.step()
    total = sum(mode.calls.values())
    print(f"\nATen calls per step: {total / steps:.1f} (over {steps} steps)")
    for where, calls in mode.calls.most_common(top):
        print(f"{calls / steps:>9.2f}  {where}")


def time_stages(collector: OnlineCollector, steps: int) -> None:
    """``OnlineCollector.step`` taken apart (the same calls), each stage timed in CPU time."""
    c, times, restarts = collector, collections.Counter(), 0

    def timed(name, function):
        started = time.perf_counter()
        result = function()
        times[name] += time.perf_counter() - started
        return result

    started = time.process_time()
    for _ in range(steps):
        active = ~c.finished
        with torch.no_grad():
            td = c._td
            td.set(MASK_KEY, active)
            if c._any_finished:
                td.set("_step", active.unsqueeze(-1))
            td = timed("policy", lambda td=td: c.policy(td))
            td = timed("env step", lambda td=td: c.env.step(td))
        timed("learning", lambda td=td: c._learn(td))
        with torch.no_grad():
            td.set(("collector", "run"), c.run_index)
            td.set(("collector", "episode"), c.episode_index)
            next_td = timed("step_mdp", lambda td=td: c.env.step_mdp(td))
            restart = timed("bookkeeping", lambda td=td, active=active: c._record(td, active))
            if restart is not None:
                restarts += 1

                def reset(next_td=next_td, restart=restart):
                    env_td = next_td.select(*c._env_keys, strict=False)
                    hints = {"restarts_terminated": True} if c._restarts_terminated else {}
                    if getattr(c, "_mask_keyword", False):
                        hints["reset_mask"] = restart
                    else:
                        env_td.set("_reset", restart.unsqueeze(-1))
                    next_td.update(c.env.reset(env_td, **hints))

                timed("restart", reset)
        c._td = next_td
    total = (time.process_time() - started) / steps
    print(f"\nCPU ms per step: {total * 1e3:.3f}; a world restarted on {restarts} of {steps} steps")
    for name, seconds in times.items():
        print(f"{seconds / steps * 1e3:>9.3f} ms  {seconds / steps / total:>5.0%}  {name}")


def compare_restarts(collector: OnlineCollector, blocks: int, steps: int) -> None:
    best = {True: float("inf"), False: float("inf")}
    for _ in range(blocks):
        for keyword in (True, False):
            collector._mask_keyword = keyword
            started = time.process_time()
            for _ in range(steps):
                collector.step()
            best[keyword] = min(best[keyword], (time.process_time() - started) / steps)
    print(
        f"\nrestarts by reset_mask: {best[True] * 1e3:.3f} ms per step, by the '_reset' entry: "
        f"{best[False] * 1e3:.3f} (best of {blocks} alternating blocks of {steps} steps)"
    )


def batched_steps() -> None:
    from factorq_trainers.commands.paper import command as paper
    from factorq_trainers.commands.paper import drivers as paper_drivers
    from factorq_trainers.compiled import fast

    if not fast.is_available():
        print("\nbatched steps: the fast path is unavailable here")
        return
    config = paper.PaperConfig(out="unused")
    print("\nbatched steps of the default paper batch (the slowest experiment's total steps)")
    for algorithm in config.methods:
        keys = paper_drivers.experiment_keys(config, algorithm)
        metrics = paper_drivers.run_fast(config, algorithm, keys, lambda e: None)
        steps = metrics["steps"].sum(dim=(1, 2)).double().view(len(config.regimes), -1)
        worst = [
            f"{world} {int(row.max()):,}" for world, row in zip(config.regimes, steps, strict=True)
        ]
        print(
            f"{algorithm:>12}: {int(steps.max()):,} (mean experiment {float(steps.mean()):,.0f}; "
            f"slowest per world: {', '.join(worst)})"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithm", choices=("q-learning", "factor-q"), default="q-learning")
    parser.add_argument("--size", type=int, default=300, help="experiments S (paper: 300)")
    parser.add_argument("--skip", type=int, default=20, help="plain steps before measuring")
    parser.add_argument("--steps", type=int, default=1500, help="steps timed per stage")
    parser.add_argument("--top", type=int, default=25, help="functions listed")
    parser.add_argument("--batched-steps", action="store_true", help="only the batch lengths")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.batched_steps:
        batched_steps()
        return
    print(f"{args.algorithm}, S = {args.size}, after {args.skip} steps")
    collectors = []
    for _ in range(2):  # one to time, one to count calls on (the same steps)
        collectors.append(build(args.algorithm, args.size))
        for _ in range(args.skip):
            collectors[-1].step()
    time_stages(collectors[0], args.steps)
    compare_restarts(collectors[0], 6, 150)
    count_calls(collectors[1], 50, args.top)  # (last: the counting mode slows what runs after)


if __name__ == "__main__":
    main()
