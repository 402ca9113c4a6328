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

``--body-flip``: the same open-loop comparison on ``factorq dependencies --sensors ring
--distractors D --sensor-noise P --seed S`` (``--distractors``, ``--noise``, ``--seed``), for a
sensor model with one flip rate for the whole body (issue 39, item 5; ``docs/decisions.md``,
"Noise with many sensors: one flip rate per body, measured"). A single sensor ``j`` as the parent
reads the clean bit the collision is, flipped with the body's rate ``eps``: with ``q`` the rate of
the clean obstacle at firing, ``P(collide | reads obstacle) = (1 - eps) q / ((1 - eps) q + eps (1
- q))`` and ``P(collide | reads free) = eps q / (eps q + (1 - eps) (1 - q))`` (both labellings,
``log 2`` each), ``q`` integrated on a grid under ``Beta(1/4, 1/4)``; "no sensor" is the
collisions under the same ``q``; pairs keep the mixture. ``eps`` is either told (the world's
``p``) or shared by the body: a log-uniform grid on ``[1e-4, 0.45]``, integrated with the other
actuators' evidence up to the firing (``P(c_a | D) ~ P(c_a) sum_eps p(eps) P(D_a | c_a, eps)
prod_{b != a} P(D_b | eps)``, ``P(D_b | eps)`` summed over ``b``'s candidates). The commitment
rule on each prefix, as in ``--streams``; printed: experiments with every actuator committed
right within 100 samples, the actuators' share, wrong first commitments per 1,000 experiments,
and (no commitment rule) experiments where, at 100 firings (or all an actuator had), every
actuator's true candidate is ahead of all its competitors (its strict supersets are not).

``--misses SETTING``: the experiments of that setting not right within 100 samples (the same
run): for each, when it became right (``inf``: not at the end), its wrong commitments and
reopenings, every actuator's firings in the whole experiment, and the actuators wrong at the end
with what they hold and the truth, in the world's sensor order (ring: 0-3 the cross, 4-7 the
diagonals ahead-left, behind-left, behind-right, ahead-right; 8 on distractors).

    .venv/bin/python benchmarks/structure_evidence.py --odds
    .venv/bin/python benchmarks/structure_evidence.py --streams ring-12-noise-10
    .venv/bin/python benchmarks/structure_evidence.py --misses ring-12-noise-10 --seed 2
    .venv/bin/python benchmarks/structure_evidence.py --body-flip --distractors 12 --noise 0.10

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from factorq_envs.permutation import permuted_dependency
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
    truth = permuted_dependency(world.dependency, orders)  # [S, A, K]
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


#: ``--body-flip``: the grids of the body's flip rate and of the clean obstacle rate at firing.
FLIP_GRID = torch.tensor(np.geomspace(1e-4, 0.45, 25))
RATE_GRID = torch.linspace(0.005, 0.995, 40, dtype=torch.float64)
_RATE_WEIGHTS = RATE_GRID**-0.75 * (1 - RATE_GRID) ** -0.75  # Beta(1/4, 1/4)
LOG_RATE_PRIOR = torch.log(_RATE_WEIGHTS / _RATE_WEIGHTS.sum())


def flip_scores(bits: torch.Tensor, collided: torch.Tensor, sets: list[tuple]) -> torch.Tensor:
    """``[n, C, E]``: every candidate's log marginal after each prefix of one actuator's firings,
    for each flip rate of ``FLIP_GRID`` (singles and "no sensor" under the body's flip model,
    pairs on the mixture, the same for every rate)."""
    first = torch.tensor([s[0] if len(s) > 0 else -1 for s in sets])
    second = torch.tensor([s[1] if len(s) > 1 else -1 for s in sets])
    bit_j = torch.where(first >= 0, bits[:, first.clamp(min=0)], 0)
    bit_k = torch.where(second >= 0, bits[:, second.clamp(min=0)], 0)
    onehot = torch.nn.functional.one_hot(bit_j + 2 * bit_k, 4).double()
    mixture = mixture_log_marginal(onehot.cumsum(0), (onehot * collided[:, None, None]).cumsum(0))
    size = torch.tensor([len(s) for s in sets])
    out = mixture.sum(-1)[:, :, None].expand(-1, -1, len(FLIP_GRID)).clone()
    n = torch.arange(1, len(collided) + 1, dtype=torch.float64)
    hits = collided.cumsum(0)
    log_q, log_not_q = torch.log(RATE_GRID), torch.log1p(-RATE_GRID)
    none = torch.logsumexp(
        hits[:, None] * log_q + (n - hits)[:, None] * log_not_q + LOG_RATE_PRIOR, 1
    )
    out[:, size == 0, :] = none[:, None, None]
    single = [s[0] for s in sets if len(s) == 1]
    reads = bits.double()[:, single]
    n1, s1 = reads.cumsum(0), (reads * collided[:, None]).cumsum(0)
    n0, s0 = n[:, None] - n1, hits[:, None] - s1
    eps, q = FLIP_GRID[None, :], RATE_GRID[:, None]  # [Q, E]
    p1 = (1 - eps) * q / ((1 - eps) * q + eps * (1 - q))
    p0 = eps * q / (eps * q + (1 - eps) * (1 - q))
    logs = [torch.log(x) for x in (p1, 1 - p1, p0, 1 - p0)]

    def labelled(n1: torch.Tensor, s1: torch.Tensor, n0: torch.Tensor, s0: torch.Tensor):
        counts = (s1, n1 - s1, s0, n0 - s0)
        total = sum(c[..., None, None] * log for c, log in zip(counts, logs, strict=True))
        return torch.logsumexp(total + LOG_RATE_PRIOR[:, None], dim=-2)  # [n, K, E]

    out[:, size == 1, :] = torch.logaddexp(
        labelled(n1, s1, n0, s0), labelled(n0, s0, n1, s1)
    ) - math.log(2)
    return out


def body_flip(distractors: int, noise: float, seed: int) -> None:
    config = DependenciesConfig(
        seed=seed, sensors="ring", distractors=distractors, sensor_noise=noise, threads=1,
        out="unused",
    )  # fmt: skip
    result = methods.run_learned_fast(config, "custom")
    state = result["_state"]
    world = config.world_of("custom")
    sensors, actuators = world.num_sensors, world.num_actuators
    orders = methods.sensor_orders(seed, config.setting_stream("custom"), config.seeds, sensors, 0)
    truth = permuted_dependency(world.dependency, orders)
    sets = candidate_sets(sensors)
    prior = candidate_log_prior(sets, "sparse")
    competitors = competitor_mask(sets)
    threshold = math.log(config.bayes_factor)
    told = int((FLIP_GRID - noise).abs().argmin())
    log_flip_prior = torch.full_like(FLIP_GRID, -math.log(len(FLIP_GRID)))
    models = ("mixture", "one flip rate per body", f"flip rate told ({FLIP_GRID[told]:.3f})")
    experiments = state["history_length"].shape[0]
    right = dict.fromkeys(models, 0)
    actuators_right = dict.fromkeys(models, 0)
    wrong = dict.fromkeys(models, 0)
    most_probable = dict.fromkeys(models, 0)  # the truth ahead of its competitors
    for i in range(experiments):
        length = int(state["history_length"][i])
        fired = state["history_action"][i, :length].long()
        where, score, evidence = {}, {}, {}
        for a in range(actuators):
            where[a] = (fired == a).nonzero().flatten()[:STREAM]
            if where[a].numel() == 0:
                continue
            raw = state["history_readings"][i, where[a]]
            bits = (raw[:, None] >> torch.arange(sensors)) & 1
            collided = (state["history_reward"][i, where[a]] < 0).double()
            score[a] = flip_scores(bits, collided, sets)
            summed = torch.logsumexp(score[a] + prior[None, :, None], dim=1)  # [n, E]
            evidence[a] = torch.cat([torch.zeros(1, len(FLIP_GRID), dtype=summed.dtype), summed])
        for model in models:
            every = every_map = True
            for a in range(actuators):
                if a not in score:
                    every = every_map = False
                    continue
                if model == "mixture":
                    log_posterior = scores(  # the learner's likelihood, prior included
                        bits_of(state, i, where[a], sensors), collided_of(state, i, where[a]),
                        sets, None,
                    )  # fmt: skip
                elif model == "one flip rate per body":
                    others = torch.zeros(score[a].shape[0], len(FLIP_GRID), dtype=torch.float64)
                    for b in evidence:
                        if b != a:
                            others += evidence[b][
                                torch.searchsorted(where[b], where[a], right=True)
                            ]
                    log_posterior = (
                        torch.logsumexp(score[a] + (others + log_flip_prior)[:, None, :], dim=2)
                        + prior
                    )
                else:
                    log_posterior = score[a][:, :, told] + prior
                target = sets.index(tuple(truth[i, a].nonzero().flatten().tolist()))
                at = log_posterior[min(SAMPLES, log_posterior.shape[0]) - 1]
                rival = torch.where(competitors[target], at, -math.inf).max()
                every_map = every_map and bool(at[target] >= rival)
                committed = False
                for step in range(log_posterior.shape[0]):
                    row = log_posterior[step]
                    best = int(row.argmax())
                    rival = torch.where(competitors[best], row, -math.inf).max()
                    if row[best] - rival >= threshold:
                        committed = True
                        if best != target:
                            wrong[model] += 1
                        elif step + 1 <= SAMPLES:
                            actuators_right[model] += 1
                        every = every and best == target and step + 1 <= SAMPLES
                        break
                every = every and committed
            right[model] += every
            most_probable[model] += every_map
    print(
        f"ring + {distractors} distractors, p = {noise:.2f}, master seed {seed}, "
        f"{experiments} experiments (the learner: right within {SAMPLES} samples "
        f"{np.mean(np.asarray(result['samples_until_right'], dtype=float) <= SAMPLES):.0%}, "
        f"wrong commitments {1000 * np.mean(result['wrong_commitments']):.0f} / 1000)"
    )
    for model in models:
        print(
            f"  {model}: experiments right within {SAMPLES} samples "
            f"{right[model] / experiments:.0%}"
            f", actuators {actuators_right[model] / (experiments * actuators):.1%}, wrong first "
            f"commitments {1000 * wrong[model] / experiments:.0f} / 1000; the truth ahead of its "
            f"competitors at {SAMPLES} firings in every actuator "
            f"{most_probable[model] / experiments:.0%}",
            flush=True,
        )


def bits_of(state: dict, i: int, index: torch.Tensor, sensors: int) -> torch.Tensor:
    return (state["history_readings"][i, index][:, None] >> torch.arange(sensors)) & 1


def collided_of(state: dict, i: int, index: torch.Tensor) -> torch.Tensor:
    return (state["history_reward"][i, index] < 0).double()


def misses(setting: str, seed: int) -> None:
    config = DependenciesConfig(seed=seed, out="unused")
    result = methods.run_learned_fast(config, setting)
    state = result["_state"]
    world = config.world_of(setting)
    orders = methods.sensor_orders(
        seed, config.setting_stream(setting), config.seeds, world.num_sensors, 0
    )
    truth = permuted_dependency(world.dependency, orders)  # [S, A, K], the agent's order
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
    parser.add_argument("--body-flip", action="store_true", help="One flip rate per body.")
    parser.add_argument("--distractors", type=int, default=12, help="--body-flip's distractors.")
    parser.add_argument("--noise", type=float, default=0.10, help="--body-flip's sensor noise.")
    parser.add_argument("--sensors", type=int, default=4, help="Sensors of the odds table.")
    parser.add_argument("--seed", type=int, default=0, help="Master seed of the streams.")
    arguments = parser.parse_args()
    if arguments.odds:
        odds_table(arguments.sensors)
    if arguments.streams:
        streams(arguments.streams, arguments.seed)
    if arguments.misses:
        misses(arguments.misses, arguments.seed)
    if arguments.body_flip:
        body_flip(arguments.distractors, arguments.noise, arguments.seed)
    if not (arguments.odds or arguments.streams or arguments.misses or arguments.body_flip):
        parser.error("give --odds, --streams SETTING, --misses SETTING and/or --body-flip")


if __name__ == "__main__":
    main()
