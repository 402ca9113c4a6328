"""What any learner can reach: a Bayes-optimal bound on finding a parent under sensor noise.

Issue 39, item 5 asks whether "95% right within 100 samples at 8% noise with 10+ sensors, wrong
commitments at most 20 per 1,000" can be met, or to show with a bound why not. This script
computes, for ``factorq dependencies``' world, the best probability with which *any* learner
names each actuator's parent sensor from ``n`` of its firings (the Bayes-optimal, maximum a
posteriori rule under the true generative model, which no learner beats), and what an ideal
Bayesian learner that commits when its posterior odds reach ``B`` gets: committed right within
``n`` firings, and wrong commitments.

**The generative model** (read from the code, ``factorq_envs.grid_functions.observe`` and
``body.base_dependency``): the static ``size x size`` world of ``layout_seed`` (6x6, 4 obstacles,
seed 0: the defaults); the ``ring`` layout's 8 clean sensors (wall or obstacle in the cell at
each offset) of the agent's cell, then ``D`` distractors (fair coins); every bit flipped with
probability ``p`` independently (``--sensor-noise``); the agent's sensors a uniformly random
permutation of these ``K = 8 + D`` bits. The ``translate`` body's actuator ``a`` collides iff the
*clean* cross sensor of its direction reads an obstacle: the collision ``y`` is that clean bit.

**Assumptions that favour the bound** (each gives the ideal learner information or freedom the
real one lacks, so the figures are upper bounds for the real learner under the sampling
assumption below):

1. *Side information.* The ideal learner is told which positions hold the distractors and where
   every ring sensor is, except for the ``--confusable`` ring sensors nearest the parent (default
   3: the parent and the two diagonals beside it, which share its wall; 5 adds the two cross
   sensors beside it): their ``m!`` arrangements over their ``m`` positions are equally likely a
   priori, and success is naming the parent's position. (Told where the distractors are loses
   nothing that matters at ``n = 100``: a distractor agrees with the collision about half the
   time, the parent ``1 - p`` of it; ``--distractor-check`` prints the exact chance that one of
   ``D`` distractors agrees at least as often as the parent, which is all a distractor could do.)
2. It knows ``p``, the collision model (a single parent), and the distribution of the clean ring
   readings at the actuator's firings.
3. *Sampling.* The firing states are i.i.d. draws of the agent's cell: uniform over the free
   cells (``--q`` unset: the stationary distribution of the uniform random walk, whose blocked
   moves stay, a symmetric chain), or reweighted so that a fraction ``q`` of the firings face an
   obstacle (a policy that has learned to avoid, ``--q 0.1``). The real firings are a Markov
   chain that repeats nearby states (less informative than i.i.d. draws); a learner that chose
   *where* to fire could do better than i.i.d. draws, the real one does not choose for that.
4. Each actuator has its ``n`` firings. In the measured experiments some actuators are fired
   fewer than 100 times in all (the policy avoids them): that caps the real learner, not the
   bound.

An experiment is "right within ``n``" when every actuator is (``factorq dependencies``' measure):
at most the smallest actuator's figure (printed ``min``), about the product when the actuators'
firings are independent (printed ``all 4``).

The likelihood of one firing under arrangement ``sigma`` is a table look-up: ``T[z^sigma, y] =
sum_c w_c [x_c[a] = y] p^{d(z^sigma, x_c)} (1 - p)^{8 - d}`` over the free cells ``c`` of weight
``w_c``, with ``d`` the Hamming distance between the arranged noisy reading and the cell's clean
ring ``x_c``; the posterior follows each firing (cumulative sums), so the committing learner's
first crossing of odds ``B`` is exact per draw.

``--streams D,...`` drops the sampling assumption: it runs ``factorq dependencies --sensors ring
--distractors D --sensor-noise P --seed S`` (compiled path) and scores each actuator's first
``n`` firings of that very run (the history the kernel keeps for pair pruning, put back in the
world's sensor order) with the same ideal learner (uniform cell weights, told ``p`` and the side
information), beside the learner's own measure of the run. Not a bound (the ideal's cell weights
are not the run's); what a learner told that much does on the data the policy gathered.

    .venv/bin/python benchmarks/structure_bound.py
    .venv/bin/python benchmarks/structure_bound.py --noise 0.08,0.10 --q 0.1 --confusable 5
    .venv/bin/python benchmarks/structure_bound.py --streams 5,12 --noise 0.08 --confusable 5

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import itertools
import math

import numpy as np
import torch

from factorq_envs.body import RING, TRANSLATE
from factorq_envs.grid_functions import sense, static_layout
from factorq_trainers.methods.experiment import check_world_options

RING_BITS = RING.num_sensors


def ring_readings(size: int, obstacles: int, layout_seed: int) -> np.ndarray:
    """The clean ring readings ``[free cells, 8]`` bool of the static world (heading 0)."""
    world = check_world_options(
        size, obstacles, 1000, layout_seed, ("static",), {"sensors": "ring"}
    )
    layout = static_layout(world)
    cells = torch.nonzero(~layout).flatten()
    heading = torch.zeros_like(cells)
    readings = sense(cells, heading, layout.unsqueeze(0).expand(len(cells), -1), world)
    return readings.numpy()


def cell_weights(clean: np.ndarray, actuator: int, q: float | None) -> np.ndarray:
    """Uniform over the free cells, or reweighted so that a fraction ``q`` face an obstacle."""
    weights = np.full(len(clean), 1.0 / len(clean))
    if q is not None:
        blocked = clean[:, actuator]
        weights = np.where(blocked, q / blocked.sum(), (1 - q) / (~blocked).sum())
    return weights


def confusable_set(actuator: int, m: int) -> list[int]:
    """The parent's ring index first, then the ring sensors that share its wall: the two
    diagonals beside it, then the cross sensors beside it (``m`` of them)."""
    direction = TRANSLATE.moves[actuator]
    beside = [k for k, d in enumerate(RING.directions) if len(d) == 2 and direction in d]
    sides = [k for k, d in enumerate(RING.directions) if len(d) == 1 and d[0] % 2 != direction % 2]
    order = [RING.directions.index((direction,)), *beside, *sides]
    if not 1 <= m <= len(order):
        raise SystemExit(f"--confusable {m}: must be 1..{len(order)}")
    return order[:m]


def likelihood_table(clean: np.ndarray, weights: np.ndarray, parent: int, p: float) -> np.ndarray:
    """``log T[v, y]``: the log probability of the noisy ring reading ``v`` (8 bits, bit ``k`` =
    sensor ``k``) and the collision ``y`` under the true arrangement."""
    codes = (clean.astype(np.int64) << np.arange(RING_BITS)).sum(axis=1)
    values = np.arange(1 << RING_BITS)
    distance = np.array([[bin(v ^ c).count("1") for c in codes] for v in values])  # [256, cells]
    per_cell = weights * p**distance * (1 - p) ** (RING_BITS - distance)
    table = np.stack([(per_cell * (clean[:, parent] == y)).sum(axis=1) for y in (0, 1)], axis=1)
    with np.errstate(divide="ignore"):
        return np.log(table)


def arrangement_maps(confusable: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """For every arrangement ``sigma`` of the confusable sensors over their positions: the map
    ``[sigmas, 256]`` from the agent's reading (bit ``j`` = position ``j``, the identity being
    the truth) to the reading in sensor order under ``sigma``, and the parent's position."""
    values = np.arange(1 << RING_BITS)
    maps, parent_position = [], []
    for image in itertools.permutations(confusable):
        sigma = dict(zip(confusable, image, strict=True))  # sensor k sits at position sigma[k]
        mapped = np.zeros_like(values)
        for k in range(RING_BITS):
            mapped |= ((values >> sigma.get(k, k)) & 1) << k
        maps.append(mapped)
        parent_position.append(sigma[confusable[0]])
    return np.stack(maps), np.array(parent_position)


def posterior_path(
    code: np.ndarray, y: np.ndarray, table: np.ndarray, maps: np.ndarray, group: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The ideal learner after each firing of ``[batch, n]`` readings ``code`` and collisions
    ``y``: the index (into the parent positions of ``group``) of the most probable position and
    its posterior, both ``[batch, n]``."""
    loglik = table[maps[:, code], y[None]]  # [sigmas, batch, n]
    cumulative = np.cumsum(loglik, axis=-1)
    mass = np.exp(cumulative - cumulative.max(axis=0, keepdims=True))
    per_position = np.einsum("ps,sbn->pbn", group.astype(float), mass)
    posterior = per_position / per_position.sum(axis=0, keepdims=True)  # [positions, batch, n]
    return posterior.argmax(axis=0), posterior.max(axis=0)


def simulate(
    clean: np.ndarray,
    actuator: int,
    p: float,
    q: float | None,
    m: int,
    n: int,
    draws: int,
    factors: list[float],
    rng: np.random.Generator,
    batch: int = 500,
) -> dict[str, np.ndarray]:
    """Monte Carlo over ``draws`` data sets of ``n`` firings: per draw, whether the MAP parent
    after each firing is right, and each committing learner's first commitment (firing, right)."""
    weights = cell_weights(clean, actuator, q)
    confusable = confusable_set(actuator, m)
    parent = confusable[0]
    table = likelihood_table(clean, weights, parent, p)
    maps, parent_position = arrangement_maps(confusable)
    positions = np.unique(parent_position)
    group = parent_position[None, :] == positions[:, None]  # [positions, sigmas]
    truth = int(np.flatnonzero(positions == parent)[0])
    map_right = np.zeros((draws, n), dtype=bool)
    first = {f: np.full(draws, n + 1) for f in factors}
    first_right = {f: np.zeros(draws, dtype=bool) for f in factors}
    for start in range(0, draws, batch):
        size = min(batch, draws - start)
        cells = rng.choice(len(clean), size=(size, n), p=weights)
        x = clean[cells]  # [size, n, 8]
        z = x ^ (rng.random(x.shape) < p)
        code = (z.astype(np.int64) << np.arange(RING_BITS)).sum(axis=-1)  # [size, n]
        y = x[..., parent].astype(np.int64)
        best, best_posterior = posterior_path(code, y, table, maps, group)
        map_right[start : start + size] = best == truth
        for f in factors:
            crossed = best_posterior >= f / (1 + f)  # odds f against all other positions
            any_crossed = crossed.any(axis=-1)
            when = np.where(any_crossed, crossed.argmax(axis=-1), n)
            first[f][start : start + size] = when + 1
            right = best[np.arange(size), np.minimum(when, n - 1)] == truth
            first_right[f][start : start + size] = any_crossed & right
    return {"map_right": map_right, "first": first, "first_right": first_right}


def learner_streams(
    distractors: int, p: float, seed: int, m: int, factor: float, n: int, seeds: int
) -> None:
    """The ideal learner (uniform cell weights, told ``p`` and the side information) on the very
    firings ``factorq dependencies --sensors ring --distractors D --sensor-noise P --seed S``
    gave the learner: each actuator's first ``n`` firings, put back into the world's sensor
    order; printed beside the learner's own measure of the same run."""
    from factorq_trainers.commands.dependencies import methods
    from factorq_trainers.commands.dependencies.config import DependenciesConfig

    config = DependenciesConfig(
        seed=seed, seeds=seeds, sensors="ring", distractors=distractors, sensor_noise=p,
        threads=1, out="unused",
    )  # fmt: skip
    result = methods.run_learned_fast(config, "custom")
    state = result["_state"]
    world = config.world_of("custom")
    sensors = world.num_sensors
    orders = methods.sensor_orders(seed, config.setting_stream("custom"), seeds, sensors, 0)
    clean = ring_readings(config.size, config.obstacles, config.layout_seed)
    actuators = [a for a, move in enumerate(TRANSLATE.moves) if move is not None]
    right = np.ones(seeds, dtype=bool)
    wrong = short = 0
    for a in actuators:
        confusable = confusable_set(a, m)
        table = likelihood_table(clean, cell_weights(clean, a, None), confusable[0], p)
        maps, parent_position = arrangement_maps(confusable)
        positions = np.unique(parent_position)
        group = parent_position[None, :] == positions[:, None]
        truth = int(np.flatnonzero(positions == confusable[0])[0])
        for i in range(seeds):
            length = int(state["history_length"][i])
            fired = state["history_action"][i, :length].long()
            index = (fired == a).nonzero().flatten()[:n]
            if index.numel() == 0:
                right[i] = False
                continue
            short += index.numel() < n
            raw = state["history_readings"][i, index].long()
            agent = ((raw[:, None] >> torch.arange(sensors)) & 1).numpy()  # agent's order
            world_bits = np.zeros_like(agent)
            world_bits[:, orders[i].numpy()] = agent  # agent's sensor j is world bit orders[i, j]
            code = (world_bits[:, :RING_BITS] << np.arange(RING_BITS)).sum(axis=1)[None]
            y = (state["history_reward"][i, index] < 0).numpy().astype(np.int64)[None]
            best, best_posterior = posterior_path(code, y, table, maps, group)
            crossed = best_posterior[0] >= factor / (1 + factor)
            if not crossed.any():
                right[i] = False
                continue
            first = int(crossed.argmax())
            if best[0, first] != truth:
                right[i] = False
                wrong += 1
    until = np.asarray(result["samples_until_right"], dtype=np.float64)
    print(
        f"ring + {distractors} distractors, p = {p:.2f}, master seed {seed}, {seeds} experiments: "
        f"learner right within {n} samples {(until <= n).mean():.0%}, wrong commitments "
        f"{1000 * np.mean(result['wrong_commitments']):.0f} / 1000; ideal learner at odds "
        f"{factor:g} on the same firings {right.mean():.0%}, wrong first commitments "
        f"{1000 * wrong / seeds:.0f} / 1000 ({short} actuators fired fewer than {n} times)"
    )


def distractor_chance(n: int, p: float, distractors: int) -> float:
    """P(some of ``distractors`` fair coins agrees with the collision at least as often as the
    parent's noisy reading) over ``n`` firings: exact, binomial sums."""
    parent = [math.comb(n, k) * (1 - p) ** k * p ** (n - k) for k in range(n + 1)]
    coin = [math.comb(n, k) / 2**n for k in range(n + 1)]
    below = np.cumsum([0.0, *coin])  # below[k]: P(coin < k)
    return float(sum(parent[k] * (1 - below[k] ** distractors) for k in range(n + 1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--noise", default="0.08,0.10", help="sensor noise rates p (comma list)")
    parser.add_argument("--q", default="", help="obstacle fractions at firing (comma list; "
                        "'' or uniform: the random walk's)")  # fmt: skip
    parser.add_argument("--confusable", type=int, default=3, help="ring sensors left unrevealed")
    parser.add_argument("--samples", default="10,20,30,50,100", help="firings n (comma list)")
    parser.add_argument("--factors", default="30,300,3000", help="commitment odds B (comma list)")
    parser.add_argument("--draws", type=int, default=4000, help="Monte Carlo data sets")
    parser.add_argument("--distractors", default="5,12", help="for --distractor-check")
    parser.add_argument("--seed", type=int, default=0, help="Monte Carlo's, or the run's")
    parser.add_argument(
        "--streams", default="", help="D,D,...: score factorq dependencies' own firings with "
        "ring + D distractors at each --noise (master seed --seed) instead of i.i.d. draws",
    )  # fmt: skip
    parser.add_argument("--seeds", type=int, default=100, help="experiments of --streams")
    parser.add_argument("--size", type=int, default=6)
    parser.add_argument("--obstacles", type=int, default=4)
    parser.add_argument("--layout-seed", type=int, default=0)
    args = parser.parse_args()
    noises = [float(v) for v in args.noise.split(",")]
    qs = [None if v in ("", "uniform") else float(v) for v in args.q.split(",")]
    samples = [int(v) for v in args.samples.split(",")]
    factors = [float(v) for v in args.factors.split(",")]
    n = max(samples)
    if args.streams:
        for d, p in itertools.product((int(v) for v in args.streams.split(",")), noises):
            learner_streams(d, p, args.seed, args.confusable, 300.0, n, args.seeds)
        return
    clean = ring_readings(args.size, args.obstacles, args.layout_seed)
    actuators = [a for a, move in enumerate(TRANSLATE.moves) if move is not None]
    rng = np.random.default_rng(args.seed)
    print(
        f"{args.size}x{args.size} static world (layout seed {args.layout_seed}, {args.obstacles} "
        f"obstacles): {len(clean)} free cells; {args.confusable} confusable ring sensors; "
        f"{args.draws} draws per actuator; obstacle fraction at firing per actuator (uniform): "
        + ", ".join(f"{clean[:, a].mean():.2f}" for a in actuators)
    )
    for p, q in itertools.product(noises, qs):
        label = "uniform" if q is None else f"{q:.2f}"
        runs = [
            simulate(clean, a, p, q, args.confusable, n, args.draws, factors, rng)
            for a in actuators
        ]
        print(f"\np = {p:.2f}, q = {label}")
        print("| rule | " + " | ".join(f"n = {k}: min, all 4" for k in samples) + " |")
        print("| --- |" + " --- |" * len(samples))
        cells = []
        for k in samples:
            each = [float(run["map_right"][:, k - 1].mean()) for run in runs]
            cells.append(f"{min(each):.4f}, {math.prod(each):.4f}")
        print("| MAP right | " + " | ".join(cells) + " |")
        for f in factors:
            cells = []
            for k in samples:
                each = [
                    float((run["first_right"][f] & (run["first"][f] <= k)).mean()) for run in runs
                ]
                cells.append(f"{min(each):.4f}, {math.prod(each):.4f}")
            wrong = sum(
                float((~run["first_right"][f] & (run["first"][f] <= n)).mean()) for run in runs
            )
            print(
                f"| committed right at odds {f:g} | " + " | ".join(cells)
                + f" | wrong first commitments within {n}: {1000 * wrong:.1f} / 1000 experiments |"
            )  # fmt: skip
    print("\nP(a distractor agrees with the collision at least as often as the parent), exact:")
    for p in noises:
        for d in (int(v) for v in args.distractors.split(",")):
            chances = ", ".join(f"n={k}: {distractor_chance(k, p, d):.2e}" for k in samples)
            print(f"  p = {p:.2f}, {d} distractors: {chances}")


if __name__ == "__main__":
    main()
