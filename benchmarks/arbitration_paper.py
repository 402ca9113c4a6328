"""The paper's experiment with arbitration ON (issue 40, item 3): does the option change a number?

``factorq paper`` runs the paper's agents, arbitration off. This runs its Factor-Q experiments
(seeds ``0 .. --seeds - 1``, the three regimes, 10 runs x 200 episodes, the same keys) on the
modular path with ``FactorQPolicy(arbitration=True)`` and ``FactorQLoss(arbitration=True)``
(``functional.arbitrated_normaliser``), compares every per-episode metric with the compiled
path's Factor-Q (arbitration off), and computes the claims C1-C5 from the arbitrated Factor-Q
against the same seeds' Q-learning (``factorq_trainers.analysis.claims``).

    .venv/bin/python benchmarks/arbitration_paper.py --seeds 100   # the whole paper, ~4 min

Prints whether every metric is equal, and each claim's value and verdict. Not a package on
purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import time

import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv

from factorq_envs.transforms import SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss
from factorq_torch.policy import FactorQPolicy
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.commands.paper.drivers import experiment_keys, run_fast
from factorq_trainers.methods import experiment


def arbitrated(config: PaperConfig) -> dict:
    """Factor-Q's experiments of ``config`` with arbitration on, on the modular path (the keys,
    env and tables of ``paper_drivers.run_modular``)."""
    keys = experiment_keys(config, "factor-q")
    grid = experiment.make_env(config.world, keys.periods, keys.world_keys)
    task, local = experiment.tabular_values("factor-q", len(keys.periods), config.world)
    agent = config.agent
    policy = FactorQPolicy(
        len(keys.periods),
        keys=keys.policy_keys,
        epsilon=agent.epsilon,
        eta=agent.eta,
        g_min=agent.g_min,
        arbitration=True,
        gamma=agent.gamma,
    )
    loss = FactorQLoss(
        task,
        local,
        gamma=agent.gamma,
        alpha=agent.alpha,
        eta=agent.eta,
        g_min=agent.g_min,
        arbitration=True,
    )
    env = TransformedEnv(grid, SplitLocalReward())
    collector = OnlineCollector(
        env,
        TensorDictSequential(task, local, policy),
        loss,
        runs=config.runs,
        episodes=config.episodes,
    )
    torch.set_num_threads(1)
    while not collector.done:
        collector.step()
    return {name: value.numpy() for name, value in collector.metrics.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=3, help="seeds per regime")
    parser.add_argument("--runs", type=int, default=10, help="runs per experiment")
    parser.add_argument("--episodes", type=int, default=200, help="episodes per run")
    args = parser.parse_args()
    config = PaperConfig(
        seeds=args.seeds, shard_seeds=args.seeds, runs=args.runs, episodes=args.episodes
    )
    units = {unit["algorithm"]: unit for unit in paper.units(config)}

    def fast(algorithm: str) -> dict:
        keys = experiment_keys(config, algorithm)
        metrics = run_fast(config, algorithm, keys, lambda episodes: None)
        return {name: value.cpu().numpy() for name, value in metrics.items()}

    started = time.perf_counter()
    plain = fast("factor-q")
    q_learning = fast("q-learning")
    on = arbitrated(config)
    seconds = time.perf_counter() - started
    equal = all((on[name] == plain[name]).all() for name in plain)
    print(
        f"{args.seeds} seeds x 3 regimes x {config.runs} runs x {config.episodes} episodes, "
        f"{int(on['steps'].sum())} Factor-Q steps ({seconds:.0f} s): every per-episode metric "
        f"of arbitrated Factor-Q equals the paper's Factor-Q: {equal}"
    )
    outcomes = [
        paper.reduced(config, units["q-learning"], "fast", q_learning),
        paper.reduced(config, units["factor-q"], "modular", on),
    ]
    claims = paper.summarise(config, outcomes)["claims"]
    for name, claim in claims.items():
        print(f"{name}: {claim['pass']} (value {claim['value']}, 95% CI {claim['ci95']})")


if __name__ == "__main__":
    main()
