"""The structure learner's cost per firing against the number of sensors (issue 27).

On the compiled path, a translate body with the ring sensors (8) and ``K - 8`` distractors, the
static 6x6 world: ``--seeds`` experiments of ``--runs`` episodes run with the learned structure
(``fast.StructureOptions``, the defaults) and with the oracle pairing (Factor-Q told the true
dependency), one thread. Prints per ``K``: the candidates ``C``, env steps per second of both
(the kernel's run, without building the batch), the throughput ratio oracle / learned (also with
the batches' set-up counted), the learner's cost per firing (learned minus oracle time per step:
every step fires one actuator) and the learner's set-up time. The world takes at most 32
distractors, so ``K`` stops at 40 here (the learner itself takes up to
``functional.MAX_SENSORS`` = 62); the work per firing is linear in the candidates
``C = 1 + K + K (K - 1) / 2``, which gives it at ``K = 64``.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_structure.py --sensors 16,32,40

``--sensor-noise 0.1`` flips every sensor bit with that probability (the noisy settings of
``factorq dependencies``: pairs enter once no single explains the firings). ``--pairs all,pruned``
(the default) times both pair modes against the same oracle run and prints
the mean number of active (counted) candidates per actuator at the end.

The machine may be shared: read the ratios of one run, not the absolute times; each batch runs
``--repeats`` times and the fastest counts (load only ever slows a run down).
Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import time

import torch

from factorq_envs.regimes import REGIME_PERIODS
from factorq_torch.base.config import AgentConfig
from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD
from factorq_torch.functional import LIKELIHOODS, candidate_sets
from factorq_trainers.compiled import fast
from factorq_trainers.methods.experiment import check_world_options, experiment_keys


def timed(
    sensors: int,
    seeds: int,
    runs: int,
    learned: bool,
    likelihood: str = "mixture",
    pairs: str = "all",
    noise: float = 0.0,
) -> tuple[float, float, int, float]:
    """Seconds to build the batch, seconds to run it, env steps (learned structure or oracle),
    the mean number of active candidates per actuator at the end (the learner's; 0 for the
    oracle)."""
    body = {"body": "translate", "sensors": "ring", "distractors": sensors - 8}
    if noise:
        body["sensor_noise"] = noise
    world = check_world_options(6, 4, 1_000, 0, ("static",), body)
    labels = [("static", index) for index in range(seeds)]
    world_keys = experiment_keys(0, STREAM_WORLD, labels)
    policy_keys = experiment_keys(0, STREAM_POLICY, labels)
    periods = torch.full((seeds,), REGIME_PERIODS["static"], dtype=torch.int64)
    generator = torch.Generator().manual_seed(0)
    orders = torch.stack([torch.randperm(sensors, generator=generator) for _ in range(seeds)])
    structure = (
        fast.StructureOptions(orders=orders, likelihood=likelihood, pairs=pairs)
        if learned
        else None
    )
    started = time.perf_counter()
    batch = fast.ExperimentBatch(
        "factor-q",
        periods,
        world,
        AgentConfig(),
        runs,
        1,
        world_keys,
        policy_keys,
        threads=1,
        structure=structure,
    )
    built = time.perf_counter()
    while not batch.done:
        batch.advance(1 << 62)
    elapsed = time.perf_counter() - built
    active = batch.learner_state()["active"].double().sum(-1).mean().item() if learned else 0.0
    return built - started, elapsed, int(batch.metrics()["steps"].sum()), active


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sensors", default="16,32,40", help="Values of K, comma-separated.")
    parser.add_argument("--seeds", type=int, default=20, help="Experiments per batch.")
    parser.add_argument("--runs", type=int, default=10, help="Episodes per experiment.")
    parser.add_argument(
        "--likelihood", default="mixture", choices=LIKELIHOODS, help="The learner's likelihood."
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        help="Times each batch is run; the fastest counts (a shared machine's load only slows).",
    )
    parser.add_argument(
        "--pairs",
        default="all,pruned",
        help="The learner's pair modes to time (functional.PAIR_MODES), comma-separated.",
    )
    parser.add_argument(
        "--sensor-noise",
        type=float,
        default=0.0,
        help="Probability that each sensor bit flips at each observation (both runs).",
    )
    arguments = parser.parse_args()
    if not fast.is_available():
        raise SystemExit(f"the compiled path is unavailable: {fast.unavailable_reason()}")
    timed(16, 2, 1, True)  # compile and warm up
    print(
        "| K | candidates | pairs | oracle steps/s | learned steps/s | oracle / learned | the "
        "same with set-up | us per firing | active candidates at the end | learned set-up s |"
    )
    print("| ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for sensors in (int(value) for value in arguments.sensors.split(",")):

        def best(*options: object, sensors: int = sensors) -> tuple[float, float, int, float]:
            return min(
                (
                    timed(
                        sensors,
                        arguments.seeds,
                        arguments.runs,
                        *options,
                        noise=arguments.sensor_noise,
                    )
                    for _ in range(arguments.repeats)
                ),
                key=lambda result: result[1],
            )

        oracle = best(False, "mixture", "all")
        oracle_rate = oracle[2] / oracle[1]
        for pairs in arguments.pairs.split(","):
            learned = best(True, arguments.likelihood, pairs)
            learned_rate = learned[2] / learned[1]
            with_set_up = ((learned[0] + learned[1]) / learned[2]) / (
                (oracle[0] + oracle[1]) / oracle[2]
            )
            per_firing = 1e6 * (1 / learned_rate - 1 / oracle_rate)
            print(
                f"| {sensors} | {len(candidate_sets(sensors))} | {pairs} | {oracle_rate:,.0f} | "
                f"{learned_rate:,.0f} | {oracle_rate / learned_rate:.1f} | {with_set_up:.1f} | "
                f"{per_firing:.2f} | {learned[3]:.0f} | {learned[0]:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
