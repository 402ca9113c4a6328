"""The local-risk layer's cost against a DQN update (issue 26's target: under 10%).

Per env step of torchrl's DQN recipe, the layer adds one ``LocalRisk`` forward on the acting
batch (the provider's values, eqs. 2-3, the mask) and one ``LocalRiskLoss`` call on the collected
transition (eq. 5 for a table, the Bayesian counts for a ``StructureLearner``). This script times
them against one DQN update of the recipe (``DQNLoss`` forward and backward, Adam, ``SoftUpdate``
on a minibatch of ``--batch`` transitions) and against the plain actor's forward, interleaved
(``--repeats`` rounds, each timing ``--calls`` calls of every part in turn, so that a change of
load on a shared machine hits them alike); the ratio is ``(layered forward - plain forward +
local loss) / DQN update`` per round, its median printed with its range. Times are this
thread's CPU time by default (``--clock cpu``: on a machine shared with other work, wall time
mostly measures the others; one thread, so the DQN update's CPU time is its time); ``--clock
wall`` times the wall clock. Run from the repository root:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_risk_layer.py

``--baseline DIR`` also times the layer of another checkout (``DIR``, e.g. ``git worktree add
/tmp/before COMMIT``) in the same rounds, interleaved with this one, and prints the ratio of the
two layers' costs per round: a before/after comparison that one machine's changing load cannot
bias. Its ``factorq_torch`` is imported as ``factorq_torch_baseline`` (its files copied to a
temporary folder with the package's name rewritten in their imports); the DQN parts are this
checkout's for both.

``--stream N`` times the layer as an agent runs it instead: per call, one layered forward and
the loss on the next of ``N`` collected transitions (a random-action rollout, cycled), so the
learner sees varied readings, actions and collisions (commitments, the change-point test, now
and then a reopening) rather than one transition repeated, and the two parts alternate as in
the recipe; the ratio is ``(step - plain forward) / DQN update``.

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import atexit
import importlib
import logging
import re
import shutil
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import DQNLoss, SoftUpdate

import factorq_torch.risk
import factorq_torch.structure
import factorq_torch.tables
from factorq_trainers.commands.risk.config import RiskConfig
from factorq_trainers.commands.risk.methods import features, make_env

logging.getLogger("torchrl").setLevel(logging.WARNING)
warnings.filterwarnings("ignore")


CLOCKS = {"cpu": time.thread_time, "wall": time.perf_counter}


def timed(function, calls: int, clock=time.thread_time) -> float:
    """Seconds per call over ``calls`` calls."""
    started = clock()
    for _ in range(calls):
        function()
    return (clock() - started) / calls


def interleaved(functions: dict, calls: dict, repeats: int, clock=time.thread_time) -> dict:
    """Per repeat, every function timed in turn (so a load change hits them all alike; every
    other repeat in the reverse order, so neither end of a round is favoured); the per-repeat
    times by name, after one warm-up call each."""
    for function in functions.values():
        function()
    times = {name: [] for name in functions}
    for repeat in range(repeats):
        order = list(functions.items())
        for name, function in order if repeat % 2 == 0 else reversed(order):
            times[name].append(timed(function, calls[name], clock))
    return times


def load_baseline(root: str) -> tuple:
    """``(risk, tables, structure)`` modules of the ``factorq_torch`` of another checkout."""
    source = Path(root) / "factorq_torch"
    if not (source / "risk.py").is_file():
        raise SystemExit(f"--baseline {root}: no factorq_torch/risk.py there")
    folder = Path(tempfile.mkdtemp(prefix="bench-risk-baseline-"))
    atexit.register(shutil.rmtree, folder, True)  # the copy is imported once; gone at exit
    target = folder / "factorq_torch_baseline"
    shutil.copytree(source, target, ignore=shutil.ignore_patterns("__pycache__"))
    for path in target.rglob("*.py"):
        path.write_text(re.sub(r"\bfactorq_torch\b", "factorq_torch_baseline", path.read_text()))
    sys.path.insert(0, str(folder))
    return tuple(
        importlib.import_module(f"factorq_torch_baseline.{name}")
        for name in ("risk", "tables", "structure")
    )


def make_provider(method: str, env, tables, structure):
    """``experiments.risk.provider`` with the given modules' classes."""
    dependency = env.base_env.dependency
    if method.endswith("+risk"):
        return tables.LocalRewardTable(1, dependency=dependency)
    actions, sensors = dependency.shape
    return structure.StructureLearner(1, num_actions=actions, num_sensors=sensors)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--calls", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--world", default="grid", choices=["grid", "minigrid"])
    parser.add_argument("--hidden", type=int, default=64, help="width of the two hidden layers")
    parser.add_argument("--clock", default="cpu", choices=sorted(CLOCKS), help="what is timed")
    parser.add_argument("--baseline", help="another checkout whose layer to time alongside")
    parser.add_argument(
        "--stream", type=int, default=0, help="time forward + loss over N real transitions"
    )
    args = parser.parse_args()
    torch.manual_seed(0)
    config = RiskConfig(hidden=args.hidden)
    env = make_env(config, args.world, 0)
    spec = env.action_spec_unbatched
    encoder, width = features(env)
    network = MLP(in_features=width, out_features=int(spec.space.n), num_cells=[config.hidden] * 2)
    head = TensorDictModule(network, in_keys=["features"], out_keys=["action_value"])
    actor = QValueActor(TensorDictSequential(encoder, head), in_keys=["cell"], spec=spec)
    loss = DQNLoss(actor, action_space=spec, delay_value=True, loss_function="l2")
    loss.make_value_estimator(gamma=config.gamma)
    target = SoftUpdate(loss, tau=config.tau)
    optimizer = torch.optim.Adam(loss.parameters(), lr=config.lr)
    data = env.rollout(args.batch, break_when_any_done=False).reshape(-1)  # [batch]
    stream = []
    if args.stream:
        collected = env.rollout(args.stream, break_when_any_done=False).reshape(-1)
        stream = [collected[i : i + 1] for i in range(args.stream)]  # (sliced before timing)
    step = env.reset()

    def update() -> None:
        value = loss(data.clone())["loss"]
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
        target.step()

    codes = {"": (factorq_torch.risk, factorq_torch.tables, factorq_torch.structure)}
    if args.baseline:
        codes["baseline"] = load_baseline(args.baseline)
    print(
        f"world {args.world}, hidden {args.hidden}x2, DQN minibatch {args.batch}, "
        f"{args.clock} time, {args.repeats} rounds"
        + (f", forward + loss over {args.stream} transitions" if args.stream else "")
    )
    print(
        "| provider | code | DQN update (us) | plain actor (us) | "
        + ("layer step: forward + loss (us) " if args.stream else "layer forward (us) ")
        + "| local loss (us) | layer / DQN update |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: |")

    def plain(actor=actor):
        with torch.no_grad():
            actor(step.clone())

    for method in ("dqn+risk", "dqn+risk-learned"):
        functions = {"update": update, "plain": plain}
        calls = {"update": max(1, args.calls // 4), "plain": args.calls}
        kinds = {}
        for code, (risk, tables, structure) in codes.items():
            local = make_provider(method, env, tables, structure)
            kinds[code] = type(local).__name__
            acting = risk.with_local_risk(actor, local, env=env)
            local_loss = risk.LocalRiskLoss(local)

            def layered(acting=acting):
                with torch.no_grad():
                    acting(step.clone())

            if stream:

                def both(acting=acting, local_loss=local_loss, at=[0]):  # noqa: B006
                    with torch.no_grad():
                        acting(step.clone())
                    local_loss(stream[at[0] % len(stream)])
                    at[0] += 1

                functions[f"layered {code}"] = both
                functions[f"loss {code}"] = lambda: None  # (inside the step)
            else:
                functions[f"layered {code}"] = layered
                functions[f"loss {code}"] = lambda ll=local_loss, t=data[:1]: ll(t)
            calls[f"layered {code}"] = calls[f"loss {code}"] = args.calls
        times = interleaved(functions, calls, args.repeats, CLOCKS[args.clock])
        median = {name: statistics.median(values) * 1e6 for name, values in times.items()}
        costs = {}
        for code in codes:
            costs[code] = [  # the layer's cost per round
                layered - plain + loss
                for plain, layered, loss in zip(
                    times["plain"], times[f"layered {code}"], times[f"loss {code}"], strict=True
                )
            ]
            ratios = [
                cost / update for cost, update in zip(costs[code], times["update"], strict=True)
            ]
            forward = median[f"layered {code}"] - median["plain"]
            loss_text = "(in step)" if stream else f"{median[f'loss {code}']:,.0f}"
            print(
                f"| {kinds[code]} | {code or 'this checkout'} | {median['update']:,.0f} | "
                f"{median['plain']:,.0f} | {forward:,.0f} | {loss_text} | "
                f"{statistics.median(ratios):.1%} (rounds {min(ratios):.1%}-{max(ratios):.1%}) |"
            )
        if args.baseline:
            cut = [a / b for a, b in zip(costs[""], costs["baseline"], strict=True)]
            print(
                f"| {kinds['']} | this / baseline layer cost | | | | | "
                f"{statistics.median(cut):.2f} (rounds {min(cut):.2f}-{max(cut):.2f}) |"
            )


if __name__ == "__main__":
    main()
