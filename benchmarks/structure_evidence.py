"""The structure learner's evidence, counted (issue 27, ``docs/decisions.md``).

Two tables behind the decisions page's arguments:

``--odds``: the posterior odds of the right single sensor against "no sensor" under the defaults
(the mixture likelihood, ``Beta(1/4, 1/4)``, the sparse prior over ``--sensors`` sensors) after
``k`` collisions in its obstacle pattern and ``m`` safe firings in its free one: how many
collisions a commitment at odds 300 needs.

``--streams SETTING``: an open-loop comparison of two likelihoods on the same firings. The
learner runs ``factorq dependencies``' setting on the compiled path (master seed ``--seed``);
each actuator's firings (the history the kernel keeps for pair pruning) are then scored afresh
under (a) the mixture likelihood of the learner, and (b) a latent-sensor likelihood for the
single sensors (the collision the clean bit, the reading a copy of it flipped at one symmetric
rate ``eps ~ Beta(a_e, b_e)``, both labellings, ``log p(r_j | c) + log p(c) - log p(r_j)`` with
``Beta(a_q, b_q)`` for the collision rate and ``Beta(a_r, b_r)`` for the reading's), "no sensor"
as ``log p(c)``, pairs on the mixture, and the commitment rule applied to each prefix: the share
of actuators committed right within 100 samples and the wrong commitments.

``--misses SETTING``: the experiments of that setting not right within 100 samples (the same
run): for each, when it became right (``inf``: not at the end), its wrong commitments and
reopenings, every actuator's firings in the whole experiment, and the actuators wrong at the end
with what they hold and the truth, in the world's sensor order (ring: 0-3 the cross, 4-7 the
diagonals ahead-left, behind-left, behind-right, ahead-right; 8 on distractors).

    .venv/bin/python benchmarks/structure_evidence.py --odds
    .venv/bin/python benchmarks/structure_evidence.py --streams ring-12-noise-10
    .venv/bin/python benchmarks/structure_evidence.py --misses ring-12-noise-10 --seed 2

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import math

import torch

from factorq_torch.functional import (
    beta_bernoulli_log_marginal,
    candidate_log_prior,
    candidate_sets,
    competitor_mask,
    mixture_log_marginal,
)
from factorq_trainers.commands.dependencies import methods
from factorq_trainers.commands.dependencies.config import DependenciesConfig

#: The latent-sensor priors tried: (a_e, b_e, a_q, b_q, a_r, b_r).
LATENT_PRIORS = (
    (1.0, 1.0, 0.25, 0.25, 0.5, 0.5),
    (0.5, 2.0, 0.25, 0.25, 0.5, 0.5),
    (0.25, 0.25, 0.25, 0.25, 0.5, 0.5),
    (1.0, 1.0, 1.0, 1.0, 1.0, 1.0),
    (0.5, 2.0, 0.5, 0.5, 0.5, 0.5),
    (0.25, 1.0, 0.25, 0.25, 0.25, 0.25),
)
SAMPLES = 100
STREAM = 200


def odds_table(sensors: int) -> None:
    sets = candidate_sets(sensors)
    prior = candidate_log_prior(sets, "sparse")

    def marginal(n: int, s: int) -> float:
        return mixture_log_marginal(torch.tensor([float(n)]), torch.tensor([float(s)])).item()

    print("| collisions k | safe firings m | odds single : no sensor |")
    print("| ---: | ---: | ---: |")
    for k in (1, 2, 3):
        for m in (5, 10, 20, 30):
            single = prior[1].item() + marginal(k, k) + marginal(m, 0)
            none = prior[0].item() + marginal(k + m, k)
            print(f"| {k} | {m} | {math.exp(single - none):,.1f} |")


def scores(
    readings: torch.Tensor, collided: torch.Tensor, sets: list[tuple], latent: tuple | None
) -> torch.Tensor:
    """``[n, C]``: every candidate's log posterior after each prefix of the firings."""
    first = torch.tensor([s[0] if len(s) > 0 else -1 for s in sets])
    second = torch.tensor([s[1] if len(s) > 1 else -1 for s in sets])
    bit_j = torch.where(first >= 0, readings[:, first.clamp(min=0)], 0)
    bit_k = torch.where(second >= 0, readings[:, second.clamp(min=0)], 0)
    pattern = bit_j + 2 * bit_k  # [n, C]
    onehot = torch.nn.functional.one_hot(pattern, 4).double()  # [n, C, 4]
    count = onehot.cumsum(0)
    successes = (onehot * collided[:, None, None]).cumsum(0)
    log_posterior = mixture_log_marginal(count, successes).sum(-1)
    if latent is not None:
        a_e, b_e, a_q, b_q, a_r, b_r = latent
        n = torch.arange(1, len(collided) + 1, dtype=torch.float64)[:, None]
        c = collided.cumsum(0)[:, None]
        log_c = beta_bernoulli_log_marginal(n, c, a_q, b_q)
        size = torch.tensor([len(s) for s in sets])
        log_posterior[:, size == 0] = log_c
        singles = (size == 1).nonzero().flatten()
        reads, hits = count[:, singles, 1], successes[:, singles, 1]
        direct = successes[:, singles, 0] + (reads - hits)  # disagreements, obstacle = collide
        inverse = hits + (count[:, singles, 0] - successes[:, singles, 0])
        flips = torch.maximum(
            beta_bernoulli_log_marginal(n.expand_as(direct), direct, a_e, b_e),
            beta_bernoulli_log_marginal(n.expand_as(inverse), inverse, a_e, b_e),
        )
        log_reading = beta_bernoulli_log_marginal(n.expand_as(reads), reads, a_r, b_r)
        log_posterior[:, singles] = flips - math.log(2) + log_c - log_reading
    return log_posterior + candidate_log_prior(sets, "sparse")


def streams(setting: str, seed: int) -> None:
    config = DependenciesConfig(seed=seed, out="unused")
    result = methods.run_learned_fast(config, setting)
    state = result["_state"]
    world = config.world_of(setting)
    sensors, actuators = world.num_sensors, world.num_actuators
    orders = methods.sensor_orders(seed, config.setting_stream(setting), config.seeds, sensors, 0)
    truth = methods._permuted(world, orders)  # [S, A, K]
    sets = candidate_sets(sensors)
    competitors = competitor_mask(sets)
    threshold = math.log(config.bayes_factor)
    experiments = state["history_length"].shape[0]
    for latent in (None, *LATENT_PRIORS):
        right = wrong = total = 0
        for i in range(experiments):
            length = int(state["history_length"][i])
            fired = state["history_action"][i, :length].long()
            for a in range(actuators):
                total += 1
                index = (fired == a).nonzero().flatten()[:STREAM]
                if index.numel() == 0:
                    continue
                raw = state["history_readings"][i, index]
                bits = (raw[:, None] >> torch.arange(sensors)) & 1
                collided = (state["history_reward"][i, index] < 0).double()
                log_posterior = scores(bits, collided, sets, latent)
                target = sets.index(tuple(truth[i, a].nonzero().flatten().tolist()))
                for step in range(len(collided)):
                    row = log_posterior[step]
                    best = int(row.argmax())
                    rival = torch.where(competitors[best], row, -math.inf).max()
                    if row[best] - rival >= threshold:
                        wrong += best != target
                        right += best == target and step + 1 <= SAMPLES
                        break
        name = "mixture" if latent is None else f"latent sensor {latent}"
        print(
            f"{name}: right within {SAMPLES} samples {right / total:.3f} of actuators, "
            f"wrong commitments {wrong} of {total}",
            flush=True,
        )


def misses(setting: str, seed: int) -> None:
    config = DependenciesConfig(seed=seed, out="unused")
    result = methods.run_learned_fast(config, setting)
    state = result["_state"]
    world = config.world_of(setting)
    orders = methods.sensor_orders(
        seed, config.setting_stream(setting), config.seeds, world.num_sensors, 0
    )
    truth = methods._permuted(world, orders)  # [S, A, K], the agent's order
    sets = candidate_sets(world.num_sensors)
    committed = state["committed"]
    for i, until in enumerate(result["samples_until_right"]):
        if until <= SAMPLES:
            continue
        wrong = []
        for a in range(world.num_actuators):
            held = sets[int(committed[i, a])] if committed[i, a] >= 0 else ()
            right = tuple(truth[i, a].nonzero().flatten().tolist())
            if held != right:
                world_order = [int(orders[i, j]) for j in held], [int(orders[i, j]) for j in right]
                wrong.append(f"actuator {a} holds {world_order[0]}, truth {world_order[1]}")
        print(
            f"experiment {i}: right from sample {until}, "
            f"{result['wrong_commitments'][i]} wrong commitments, "
            f"{result['reopened'][i]} reopenings, firings {state['samples'][i].tolist()}"
            + ("; " + "; ".join(wrong) if wrong else "")
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--odds", action="store_true", help="The odds table.")
    parser.add_argument("--streams", metavar="SETTING", help="The open-loop comparison.")
    parser.add_argument("--misses", metavar="SETTING", help="The experiments not right.")
    parser.add_argument("--sensors", type=int, default=4, help="Sensors of the odds table.")
    parser.add_argument("--seed", type=int, default=0, help="Master seed of the streams.")
    arguments = parser.parse_args()
    if arguments.odds:
        odds_table(arguments.sensors)
    if arguments.streams:
        streams(arguments.streams, arguments.seed)
    if arguments.misses:
        misses(arguments.misses, arguments.seed)
    if not (arguments.odds or arguments.streams or arguments.misses):
        parser.error("give --odds, --streams SETTING and/or --misses SETTING")


if __name__ == "__main__":
    main()
