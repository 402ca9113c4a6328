"""The local-risk layer's cost against a DQN update (issue 26's target: under 10%).

Per env step of torchrl's DQN recipe, the layer adds one ``LocalRisk`` forward on the acting
batch (the provider's values, eqs. 2-3, the mask) and one ``LocalRiskLoss`` call on the collected
transition (eq. 5 for a table, the Bayesian counts for a ``StructureLearner``). This script times
them against one DQN update of the recipe (``DQNLoss`` forward and backward, Adam, ``SoftUpdate``
on a minibatch of ``--batch`` transitions) and against the plain actor's forward, the medians of
``--repeats`` timings of ``--calls`` calls each. Run from the repository root:

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
from factorq_trainers.risk_experiment import RiskConfig, features, make_env, provider

logging.getLogger("torchrl").setLevel(logging.WARNING)
warnings.filterwarnings("ignore")


def per_call(function, calls: int, repeats: int) -> float:
    """Median seconds per call."""
    function()  # warm-up
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        for _ in range(calls):
            function()
        times.append((time.perf_counter() - started) / calls)
    return statistics.median(times)


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

    with torch.no_grad():
        act_plain = per_call(lambda: actor(step.clone()), args.calls, args.repeats)
    dqn = per_call(update, args.calls // 4, args.repeats)
    print(
        f"world {args.world}, hidden {args.hidden}x2; DQN update on {args.batch} transitions: "
        f"{dqn * 1e6:,.0f} us"
    )
    print(f"plain actor forward: {act_plain * 1e6:,.0f} us")
    print("| provider | layer forward (us) | local loss per transition (us) | layer / DQN update |")
    print("| --- | ---: | ---: | ---: |")
    for method in ("dqn+risk-oracle", "dqn+risk-learned"):
        local = provider(method, env)
        acting = with_local_risk(actor, local, env=env)
        local_loss = LocalRiskLoss(local)
        transition = data[:1]
        with torch.no_grad():
            forward = per_call(lambda acting=acting: acting(step.clone()), args.calls, args.repeats)
        learn = per_call(lambda ll=local_loss, t=transition: ll(t), args.calls, args.repeats)
        added = forward - act_plain + learn
        print(
            f"| {type(local).__name__} | {(forward - act_plain) * 1e6:,.0f} | {learn * 1e6:,.0f} "
            f"| {added / dqn:.1%} |"
        )


if __name__ == "__main__":
    main()
