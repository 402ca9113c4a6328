"""The local-risk layer's cost against a DQN update (issue 26's target: under 10%).

Per env step of torchrl's DQN recipe, the layer adds one ``LocalRisk`` forward on the acting
batch (the provider's values, eqs. 2-3, the mask) and one ``LocalRiskLoss`` call on the collected
transition (eq. 5 for a table, the Bayesian counts for a ``StructureLearner``). This script times
them against one DQN update of the recipe (``DQNLoss`` forward and backward, Adam, ``SoftUpdate``
on a minibatch of ``--batch`` transitions) and against the plain actor's forward, interleaved
(``--repeats`` rounds, each timing ``--calls`` calls of every part in turn, so that a change of
load on a shared machine hits them alike); the ratio is ``(layered forward - plain forward +
local loss) / DQN update`` per round, its median printed with its range. Run from the
repository root:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_risk_layer.py

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
import warnings

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

from factorq_torch.risk import LocalRiskLoss, with_local_risk
from factorq_trainers.experiments.risk import RiskConfig, features, make_env, provider

logging.getLogger("torchrl").setLevel(logging.WARNING)
warnings.filterwarnings("ignore")


def timed(function, calls: int) -> float:
    """Seconds per call over ``calls`` calls."""
    started = time.perf_counter()
    for _ in range(calls):
        function()
    return (time.perf_counter() - started) / calls


def interleaved(functions: dict, calls: dict, repeats: int) -> dict:
    """Per repeat, every function timed in turn (so a load change hits them all alike); the
    per-repeat times by name, after one warm-up call each."""
    for function in functions.values():
        function()
    times = {name: [] for name in functions}
    for _ in range(repeats):
        for name, function in functions.items():
            times[name].append(timed(function, calls[name]))
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--world", default="grid", choices=["grid", "minigrid"])
    parser.add_argument("--hidden", type=int, default=64, help="width of the two hidden layers")
    args = parser.parse_args()
    torch.manual_seed(0)
    config = RiskConfig(hidden=args.hidden)
    env = make_env(config, args.world, 0)
    spec = env.action_spec_unbatched
    encoder, width = features(env)
    network = MLP(in_features=width, out_features=int(spec.space.n), num_cells=[config.hidden] * 2)
    head = TensorDictModule(network, in_keys=["observation"], out_keys=["action_value"])
    actor = QValueActor(TensorDictSequential(encoder, head), in_keys=["cell"], spec=spec)
    loss = DQNLoss(actor, action_space=spec, delay_value=True, loss_function="l2")
    loss.make_value_estimator(gamma=config.gamma)
    target = SoftUpdate(loss, tau=config.tau)
    optimizer = torch.optim.Adam(loss.parameters(), lr=config.lr)
    data = env.rollout(args.batch, break_when_any_done=False).reshape(-1)  # [batch]
    step = env.reset()

    def update() -> None:
        value = loss(data.clone())["loss"]
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
        target.step()

    print(f"world {args.world}, hidden {args.hidden}x2, DQN minibatch {args.batch}")
    print(
        "| provider | DQN update (us) | plain actor (us) | layer forward (us) | local loss (us) "
        "| layer / DQN update |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for method in ("dqn+risk-oracle", "dqn+risk-learned"):
        local = provider(method, env)
        acting = with_local_risk(actor, local, env=env)
        local_loss = LocalRiskLoss(local)
        transition = data[:1]

        def plain(actor=actor):
            with torch.no_grad():
                actor(step.clone())

        def layered(acting=acting):
            with torch.no_grad():
                acting(step.clone())

        functions = {
            "update": update,
            "plain": plain,
            "layered": layered,
            "loss": lambda ll=local_loss, t=transition: ll(t),
        }
        calls = {"update": max(1, args.calls // 4), "plain": args.calls, "layered": args.calls,
                 "loss": args.calls}  # fmt: skip
        times = interleaved(functions, calls, args.repeats)
        ratios = [
            (layered - plain + loss) / update
            for update, plain, layered, loss in zip(
                times["update"], times["plain"], times["layered"], times["loss"], strict=True
            )
        ]
        median = {name: statistics.median(values) * 1e6 for name, values in times.items()}
        print(
            f"| {type(local).__name__} | {median['update']:,.0f} | {median['plain']:,.0f} | "
            f"{median['layered'] - median['plain']:,.0f} | {median['loss']:,.0f} | "
            f"{statistics.median(ratios):.1%} (repeats {min(ratios):.1%}-{max(ratios):.1%}) |"
        )


if __name__ == "__main__":
    main()
