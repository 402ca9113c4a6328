"""The structure learner (issue 12): marginal likelihoods, posterior, commitment, reopening."""

from __future__ import annotations

import math
from fractions import Fraction

import pytest
import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import TransformedEnv

from factorq_envs import FactoredGridEnv, SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.functional import (
    SPARSE_PAIR_MASS,
    beta_bernoulli_log_marginal,
    candidate_log_prior,
    candidate_sets,
    competitor_mask,
    flip_log_marginal,
    has_minority,
    mixture_log_marginal,
)
from factorq_torch.objectives import FactorQLoss
from factorq_torch.policy import FactorQPolicy
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import TaskQTable


def test_beta_bernoulli_log_marginal_matches_hand_computation():
    # Beta(1, 1): n = 3, s = 1 -> B(2, 3) / B(1, 1) = 1! 2! / 4! = 1/12
    # Beta(2, 1): n = 3, s = 1 -> B(3, 3) / B(2, 1) = (2! 2! / 5!) / (1! 0! / 2!) = (4/120) * 2
    # n = s = 0 -> 0 (no data); a fractional success s = 0.5 of n = 1 with Beta(1, 1):
    # Gamma(1.5) Gamma(1.5) / Gamma(3) = (sqrt(pi) / 2)**2 / 2 = pi / 8
    count = torch.tensor([3.0, 0.0, 1.0])
    successes = torch.tensor([1.0, 0.0, 0.5])
    got = beta_bernoulli_log_marginal(count, successes)
    assert got.dtype == torch.float64
    expected = torch.tensor([math.log(1 / 12), 0.0, math.log(math.pi / 8)], dtype=torch.float64)
    assert torch.allclose(got, expected, atol=1e-12)
    got = beta_bernoulli_log_marginal(torch.tensor([3.0]), torch.tensor([1.0]), 2.0, 1.0)
    assert math.isclose(got.item(), math.log(4 / 120 * 2), abs_tol=1e-12)


def test_candidates_are_none_singles_then_pairs_and_larger_sets_are_refused():
    assert candidate_sets(3) == [(), (0,), (1,), (2,), (0, 1), (0, 2), (1, 2)]
    assert candidate_sets(3, max_parents=1) == [(), (0,), (1,), (2,)]
    with pytest.raises(ValueError, match="max_parents=3 is past the cap of 2"):
        candidate_sets(3, max_parents=3)
    with pytest.raises(ValueError, match="max_parents=3"):
        StructureLearner(1, num_actions=1, num_sensors=4, max_parents=3)


def test_each_size_has_the_same_prior_mass():
    prior = candidate_log_prior(candidate_sets(3)).exp()  # sizes 0, 1, 2: 1, 3, 3 candidates
    expected = torch.tensor([1 / 3] + [1 / 9] * 6, dtype=torch.float64)
    assert torch.allclose(prior, expected)
    assert torch.allclose(
        candidate_log_prior(candidate_sets(3), "uniform").exp(), prior * 0 + 1 / 7
    )


def test_the_sparse_prior_gives_all_pairs_a_hundredth_of_a_size():
    sparse = candidate_log_prior(candidate_sets(3), "sparse").exp()  # 1, 3, 3 candidates
    total = 2 + SPARSE_PAIR_MASS
    expected = [1 / total] + [1 / (3 * total)] * 3 + [SPARSE_PAIR_MASS / (3 * total)] * 3
    assert torch.allclose(sparse, torch.tensor(expected, dtype=torch.float64))
    # without pairs it is the size prior
    singles = candidate_sets(3, max_parents=1)
    assert torch.allclose(
        candidate_log_prior(singles, "sparse"), candidate_log_prior(singles, "size")
    )


def test_competitors_are_all_but_the_strict_supersets_and_singles_compete_with_none():
    sets = candidate_sets(2)  # (), (0,), (1,), (0, 1)
    mask = competitor_mask(sets)
    assert mask[0].tolist() == [False, True, True, False]  # none: the singles
    assert mask[1].tolist() == [True, False, True, False]  # (0,): not its superset (0, 1)
    assert mask[3].tolist() == [True, True, True, False]  # the pair: everything else


def test_bad_options_are_refused_by_name():
    with pytest.raises(ValueError, match="bayes_factor=1"):
        StructureLearner(1, num_actions=1, num_sensors=2, bayes_factor=1)
    with pytest.raises(ValueError, match="bayes_factor=0.5"):
        StructureLearner(1, num_actions=1, num_sensors=2, bayes_factor=0.5)
    with pytest.raises(ValueError, match="prior_a"):
        StructureLearner(1, num_actions=1, num_sensors=2, prior_a=0.0)
    with pytest.raises(ValueError, match="reopen_factor=1"):
        StructureLearner(1, num_actions=1, num_sensors=2, reopen_factor=1)
    assert StructureLearner(1, num_actions=1, num_sensors=2).reopen_factor == 300.0
    with pytest.raises(ValueError, match="noisy_reopen_factor"):
        StructureLearner(1, num_actions=1, num_sensors=2, noisy_reopen_factor=0.5)
    learner = StructureLearner(1, num_actions=1, num_sensors=2, reopen_factor=50.0)
    assert learner.noisy_reopen_factor == 50.0  # None: the reopening factor's


#: The hand computations below are with Beta(1, 1), the size prior and the pattern likelihood
#: (not the defaults).
HAND = {"prior_a": 1.0, "prior_b": 1.0, "prior": "size", "likelihood": "pattern"}


def test_posterior_and_weighted_prediction_match_hand_computation():
    # Two firings of actuator 0 with K = 2: readings (1, 0) collided, readings (0, 1) did not.
    # log p(D | c): none n=2, s=1: 1!1!/3! = 1/6; (0,): patterns 1 and 0 once each: 1/2 * 1/2;
    # (1,) and (0, 1): likewise 1/4. Prior by size: 1/3, 1/6, 1/6, 1/3.
    # Posterior ~ 1/18, 1/24, 1/24, 1/12 = (2, 1.5, 1.5, 3) / 8.
    learners = {
        prediction: StructureLearner(
            1, num_actions=2, num_sensors=2, bayes_factor=1e9, prediction=prediction, **HAND
        )
        for prediction in ("posterior", "optimistic", "map", "committed")
    }
    for learner in learners.values():
        learner.update_running_mean(
            torch.tensor([[True, False]]), torch.tensor([0]), torch.tensor([[-1.0, 0.0]])
        )
        learner.update_running_mean(
            torch.tensor([[False, True]]), torch.tensor([0]), torch.tensor([[0.0, 0.0]])
        )
    learner = learners["posterior"]
    expected = torch.tensor([2.0, 1.5, 1.5, 3.0], dtype=torch.float64) / 8
    assert torch.allclose(learner.posterior()[0, 0], expected)
    # Under (1, 0): none predicts -1/2, every other candidate -1 (its pattern's one collision):
    # 0.25 * -0.5 + 0.75 * -1 = -0.875; actuator 1 never fired: 0.
    readings = torch.tensor([[True, False]])
    assert learner.local_values(readings).tolist() == [[-0.875, 0.0]]
    assert learner.samples.tolist() == [[2, 0]]
    # optimistic: every candidate is plausible at this Bayes factor, the largest mean is none's;
    # map: (0, 1), the most probable, saw a collision under (1, 0); committed: nothing yet
    assert learners["optimistic"].local_values(readings).tolist() == [[-0.5, 0.0]]
    assert learners["map"].local_values(readings).tolist() == [[-1.0, 0.0]]
    assert learners["committed"].local_values(readings).tolist() == [[0.0, 0.0]]
    # under (0, 1) every candidate but none predicts 0: optimistic 0, map ((0, 1)) 0
    readings = torch.tensor([[False, True]])
    assert learners["optimistic"].local_values(readings).tolist() == [[0.0, 0.0]]
    assert learners["map"].local_values(readings).tolist() == [[0.0, 0.0]]


def test_optimistic_prediction_ignores_the_implausible():
    # K = 2, single sensors only: (1, 1) collided three times, (0, 0) did not, three times.
    # log p(D | c): none n=6, s=3: 3!3!/7! = 1/140; (0,) and (1,): (3!/4!)^2 = 1/16. Prior 1/2,
    # 1/4, 1/4: posterior ~ 1/280, 1/64, 1/64. At a Bayes factor of 3 none (280/64 = 4.4 below
    # the best) is ruled out and nothing commits (the two sensors tie; none led by at most 2 on
    # the way); under (1, 1) both remaining candidates predict -1, and none's -1/2 no longer
    # counts. At 1e9 it does.
    values = {}
    for bayes_factor in (3.0, 1e9):
        learner = StructureLearner(
            1, num_actions=1, num_sensors=2, max_parents=1, bayes_factor=bayes_factor, **HAND
        )
        for readings, reward in (((True, True), -1.0), ((False, False), 0.0)) * 3:
            learner.update_running_mean(
                torch.tensor([readings]), torch.tensor([0]), torch.full((1, 1), reward)
            )
        assert learner.committed.tolist() == [[-1]]
        values[bayes_factor] = learner.local_values(torch.tensor([[True, True]])).tolist()
        if bayes_factor == 3.0:
            assert learner.plausible_cache[0, 0].tolist() == [False, True, True]
            # under (1, 0) sensor 1's pattern 0 was safe: optimistic 0
            assert learner.local_values(torch.tensor([[True, False]])).tolist() == [[0.0]]
    assert values == {3.0: [[-1.0]], 1e9: [[-0.5]]}


def _feed(learner, steps, parent, generator, noise=0.0):
    """``steps`` firings of actuator 0 under random readings; sensor ``parent`` decides."""
    for _ in range(steps):
        sensors = (
            torch.rand(learner.num_experiments, learner.num_sensors, generator=generator) < 0.5
        )
        collided = sensors[:, parent]
        if noise:
            flip = torch.rand(learner.num_experiments, generator=generator) < noise
            collided = collided ^ flip
        reward = torch.zeros(learner.num_experiments, learner.num_actions)
        reward[:, 0] = -collided.float()
        action = torch.zeros(learner.num_experiments, dtype=torch.int64)
        learner.update_running_mean(sensors, action, reward)


def test_commits_to_the_deciding_sensor_and_reopens_when_the_body_changes():
    generator = torch.Generator().manual_seed(0)
    learner = StructureLearner(16, num_actions=1, num_sensors=8, window=50)
    _feed(learner, 60, parent=3, generator=generator)
    assert learner.is_committed().all()
    assert (learner.structure()[:, 0].nonzero()[:, 1] == 3).all()
    _feed(learner, 150, parent=5, generator=generator)  # the body changed
    assert (learner.reopened >= 1).all()
    assert learner.is_committed().all()
    assert (learner.structure()[:, 0].nonzero()[:, 1] == 5).all()


def _fire(learner, sensor, collided):
    """One firing of actuator 0 of every experiment with sensor 0 reading ``sensor``."""
    readings = torch.full((learner.num_experiments, learner.num_sensors), bool(sensor))
    reward = torch.zeros(learner.num_experiments, learner.num_actions)
    reward[:, 0] = -float(collided)
    learner.update_running_mean(
        readings, torch.zeros(learner.num_experiments, dtype=torch.int64), reward
    )


def _committed_after(learner, firings):
    for sensor, collided in firings:
        _fire(learner, sensor, collided)
    return learner.committed[0, 0].item()


def test_the_noise_gate_needs_a_minority_outcome_under_the_commitment():
    # one sensor that decides, Bayes factor 3: 8 clean firings commit to {0}; one more with a
    # collision in the "free" pattern first makes the commitment rest on data against a
    # pattern's majority. Then a changed body (the sensor's meaning inverted): the default test
    # reopens, the noisy odds of 1e300 do not, but only where noise was seen
    clean = [(1, 1), (0, 0)] * 4
    noisy = [(0, 1)] + clean + [(0, 0)] * 2
    changed = [(1, 0), (0, 1)] * 20
    for firings, expect_noise in ((clean, False), (noisy, True)):
        for factor, reopens in ((None, True), (1e300, not expect_noise)):
            learner = StructureLearner(
                1,
                num_actions=1,
                num_sensors=1,
                bayes_factor=3.0,
                window=10,
                noisy_reopen_factor=factor,
            )
            assert _committed_after(learner, firings) == 1  # {0}
            assert learner.noise_seen.tolist() == [expect_noise]
            _committed_after(learner, changed)
            assert (learner.reopened[0, 0].item() > 0) == reopens, (firings, factor)
    # a state saved before the flag existed loads, with the flag clear (one threshold, as then)
    learner.noise_seen.fill_(True)
    state = learner.state_dict()
    del state["noise_seen"]
    learner.load_state_dict(state)
    assert learner.noise_seen.tolist() == [False] and "noise_seen" not in state
    learner.noise_seen.fill_(True)
    learner.reset()
    assert learner.noise_seen.tolist() == [False]
    # has_minority by hand: [n, s] per pattern
    count = torch.tensor([[4.0, 4.0], [4.0, 4.0], [0.0, 3.0]])
    successes = torch.tensor([[0.0, 4.0], [1.0, 4.0], [0.0, 1.5]])
    assert has_minority(count, successes).tolist() == [False, True, True]


def test_a_reopening_forgets_the_whole_body_or_one_actuator():
    for reopen in ("body", "actuator"):
        generator = torch.Generator().manual_seed(0)
        learner = StructureLearner(4, num_actions=2, num_sensors=4, window=50, reopen=reopen)
        _feed(learner, 60, parent=3, generator=generator)
        learner.committed[:, 1] = 2  # actuator 1 holds a commitment of its own
        learner.count[:, 1] = 1.0
        before = learner.reopened.clone()
        _feed(learner, 150, parent=1, generator=generator)  # actuator 0's body changed
        assert (learner.reopened[:, 0] > before[:, 0]).all()
        assert learner.reopened[:, 1].eq(0).all()  # only the test that fired counts
        if reopen == "body":  # actuator 1 forgot too, and predicts from nothing
            assert learner.committed[:, 1].eq(-1).all() and learner.count[:, 1].eq(0).all()
        else:
            assert learner.committed[:, 1].eq(2).all() and learner.count[:, 1].eq(1).all()


def test_masked_experiments_do_not_learn():
    learner = StructureLearner(2, num_actions=1, num_sensors=2)
    learner.update_running_mean(
        torch.tensor([[True, False]] * 2),
        torch.tensor([0, 0]),
        torch.tensor([[-1.0], [-1.0]]),
        mask=torch.tensor([True, False]),
    )
    assert learner.samples.tolist() == [[1], [0]]
    assert learner.count[1].sum() == 0
    learner.reset()
    assert learner.samples.sum() == 0 and learner.count.sum() == 0


def test_static_world_location_tied_sensors_do_not_fool_it():
    # Random walk in the static world; the learner sees the four proximity bits *and* the four
    # bump bits of the previous step (tied to the location: the same face's bump, the opposite
    # proximity bit); only proximity bit a decides actuator a's collision.
    count = 16
    env = FactoredGridEnv(size=6, num_obstacles=5, obstacle_period=0, batch_size=(count,), seed=1)
    learner = StructureLearner(count, num_actions=4, num_sensors=8)
    generator = torch.Generator().manual_seed(1)
    td = env.reset()
    wrong = torch.zeros(count, 4, dtype=torch.bool)
    truth = torch.cat([torch.eye(4, dtype=torch.bool), torch.zeros(4, 4, dtype=torch.bool)], 1)
    for _ in range(500):
        readings = torch.cat([td["sensors"], td["bump"]], dim=-1)  # [S, 8], before acting
        td["action"] = torch.randint(0, 4, (count,), generator=generator)
        td = env.step(td)
        learner.update_running_mean(readings, td["action"], td["next", "collision"])
        wrong |= learner.is_committed() & ~(learner.structure() == truth).all(-1)
        td = env.step_mdp(td)
        done = td["done"].squeeze(-1)
        if done.any():
            td["_reset"] = done.unsqueeze(-1)
            td = env.reset(td)
    assert not wrong.any()
    assert learner.is_committed().float().mean() >= 0.9


def test_it_is_a_local_value_provider_for_the_factorq_loss_policy_and_collector():
    count = 3
    base = FactoredGridEnv(size=4, num_obstacles=2, obstacle_period=1, batch_size=(count,), seed=0)
    env = TransformedEnv(base, SplitLocalReward())
    task = TaskQTable(count, num_cells=16)
    learner = StructureLearner(count, num_actions=4, num_sensors=4)
    policy = TensorDictSequential(task, learner, FactorQPolicy(count, seed=0))
    collector = OnlineCollector(env, policy, FactorQLoss(task, learner), runs=2, episodes=2)
    metrics = collector.run()
    assert int(learner.samples.sum()) == int(metrics["steps"].sum())
    td = policy(env.reset())
    assert td["local_value"].shape == (count, 4) and td["local_value"].dtype == torch.float32


# -- noisy sensors (issue 27) ---------------------------------------------------------------------


def _sequence_probability(outcomes: list[int], a: Fraction, b: Fraction) -> Fraction:
    """p(y_1..y_n) under Beta(a, b) by the chain rule (Polya urn): each success has probability
    (a + s) / (a + b + i), each failure (b + f) / (a + b + i); exact rationals, no lgamma."""
    probability, successes, failures = Fraction(1), 0, 0
    for index, outcome in enumerate(outcomes):
        if outcome:
            probability *= (a + successes) / (a + b + index)
            successes += 1
        else:
            probability *= (b + failures) / (a + b + index)
            failures += 1
    return probability


def test_mixture_marginal_matches_hand_computation():
    # Clean Beta(1/4, 1/4), noisy Beta(2, 2), prior odds noisy : clean = 1 : 4 (weights 4/5, 1/5).
    # n = 3, s = 0: clean (1/4)/(1/2) * (5/4)/(3/2) * (9/4)/(5/2) = 3/8, * 4/5 = 3/10;
    #   noisy 2/4 * 3/5 * 4/6 = 1/5, * 1/5 = 1/25: the clean level, log(3/10).
    # n = 0: no data, 0 whatever the level.
    # At odds 1 : 1 (weights 1/2) a coin, n = 12, s = 6: clean (1/4 * 5/4 * ... * 21/4)**2 /
    #   (1/2 * 3/2 * ... * 23/2) = 663/19689472, noisy (2 * 3 * ... * 7)**2 / (4 * 5 * ... * 15)
    #   = 1/8580: the noisy level wins (about 3.5 times as probable), log(1/17160).
    a, b = Fraction(1, 4), Fraction(1, 4)
    coin = [1, 0] * 6
    assert _sequence_probability([0, 0, 0], a, b) * Fraction(4, 5) == Fraction(3, 10)
    assert _sequence_probability(coin, a, b) == Fraction(663, 19689472)
    assert _sequence_probability(coin, Fraction(2), Fraction(2)) == Fraction(1, 8580)
    got = mixture_log_marginal(
        torch.tensor([3.0, 0.0]), torch.tensor([0.0, 0.0]), 0.25, 0.25, (2.0, 2.0), 0.25
    )
    expected = torch.tensor([math.log(3 / 10), 0.0], dtype=torch.float64)
    assert torch.allclose(got, expected, atol=1e-12)
    got = mixture_log_marginal(
        torch.tensor([12.0]), torch.tensor([6.0]), 0.25, 0.25, (2.0, 2.0), 1.0
    )
    assert math.isclose(got.item(), math.log(1 / 17160), abs_tol=1e-12)


def test_flip_marginal_matches_hand_computation():
    # A candidate with two patterns under Beta(1, 1) on the flip rate: pattern 0 seen 3 times with
    # 1 collision (label "no", 1 disagreement), pattern 1 seen 2 times with 2 (label "yes", 0):
    # m = 1 of n = 5, v = 2 labels: B(2, 5) / B(1, 1) / 4 = (1! 4! / 6!) / 4 = 1/30 / 4 = 1/120.
    got = flip_log_marginal(torch.tensor([[3.0, 2.0]]), torch.tensor([[1.0, 2.0]]), 1.0, 1.0)
    assert math.isclose(got.item(), math.log(1 / 120), abs_tol=1e-12)


def test_mixture_posterior_of_the_learner_matches_hand_computation():
    # K = 1, single sensors only, uniform prior (1/2 each), defaults otherwise (Beta(1/4, 1/4)
    # clean, Beta(2, 2) noisy at odds 1/4): the sensor read 1 and collided 12 times, read 0 and
    # did not collide 12 times, then read 0 and collided once (a flipped reading).
    # (0,): pattern 1, n = 12, s = 12; pattern 0, n = 13, s = 1; none: n = 25, s = 13.
    # Each pattern at its more probable level (exact rationals below): the sensor wins.
    learner = StructureLearner(1, num_actions=1, num_sensors=1, prior="uniform", bayes_factor=1e9)
    on, off = torch.tensor([[True]]), torch.tensor([[False]])
    for readings, reward in [(on, -1.0)] * 12 + [(off, 0.0)] * 12 + [(off, -1.0)]:
        learner.update_running_mean(readings, torch.tensor([0]), torch.tensor([[reward]]))
    a, clean, noisy = Fraction(1, 4), Fraction(4, 5), Fraction(1, 5)

    def pattern(outcomes):
        return max(
            _sequence_probability(outcomes, a, a) * clean,
            _sequence_probability(outcomes, Fraction(2), Fraction(2)) * noisy,
        )

    sensor = pattern([1] * 12) * pattern([0] * 12 + [1])
    none = pattern([1] * 12 + [0] * 12 + [1])
    log_posterior = learner.log_posterior()[0, 0]
    assert math.isclose(
        (log_posterior[1] - log_posterior[0]).item(), math.log(sensor / none), abs_tol=1e-9
    )
    assert sensor / none > 1e5  # about 3.8e5


def test_the_mixture_commits_to_a_sensor_that_reads_wrong_15_percent_of_the_time():
    # One actuator, K = 6; sensor 2 decides the collision but reads wrong 15% of the time.
    # Fired 60 times per experiment, 12 experiments: the mixture commits to sensor 2 in nearly
    # all (a margin for any CPU: the counts are integral, the outcome is exact anyway).
    def run(likelihood, seed):
        learner = StructureLearner(1, num_actions=1, num_sensors=6, likelihood=likelihood)
        generator = torch.Generator().manual_seed(seed)
        for _ in range(60):
            truth = torch.rand(1, 6, generator=generator) < 0.3
            flips = torch.rand(1, 6, generator=generator) < 0.15
            reward = -truth[:, 2:3].float()
            learner.update_running_mean(truth ^ flips, torch.tensor([0]), reward)
        return learner.structure()[0, 0].nonzero().flatten().tolist()

    assert sum(run("mixture", seed) == [2] for seed in range(12)) >= 10


def test_an_unknown_likelihood_is_refused_by_name():
    with pytest.raises(ValueError, match="likelihood='noisy' is unknown"):
        StructureLearner(1, num_actions=1, num_sensors=2, likelihood="noisy")


def test_competitor_mask_is_the_definition_for_every_small_body():
    # the vectorised mask against the definition, pair by pair: c' competes with c unless it is
    # c itself or a strict superset of it; "no sensor" competes with the single sensors only
    for sensors in (1, 2, 3, 5):
        for max_parents in (0, 1, 2):
            sets = candidate_sets(sensors, max_parents)
            members = [frozenset(parents) for parents in sets]
            expected = torch.tensor(
                [
                    [
                        i != j and (len(other) == 1 if not best else not best < other)
                        for j, other in enumerate(members)
                    ]
                    for i, best in enumerate(members)
                ]
            )
            assert torch.equal(competitor_mask(sets), expected), (sensors, max_parents)


# -- pair pruning (pairs="pruned"; docs/decisions.md, "Learned dependencies with noisy sensors") --


def _pruned_and_all(**options):
    return [
        StructureLearner(1, num_actions=1, num_sensors=3, pairs=pairs, **options)
        for pairs in ("pruned", "all")
    ]


def test_a_pair_enters_when_no_single_explains_and_one_of_its_singles_is_plausible():
    # K = 3: (), (0,), (1,), (2,), (0, 1), (0, 2), (1, 2). Sparse prior: p(none) = 1/2.01,
    # p(single) = 1/(3 * 2.01), p(pair) = 0.01/(3 * 2.01); Bayes factor 2.5 (log 2.5 = 0.916) and
    # Beta(1, 1) per pattern ("pattern": a sequence with s of n collisions has s! (n - s)! /
    # (n + 1)!). No pair is active before any data ("no sensor" explains every firing).
    options = dict(bayes_factor=2.5, prior="sparse", likelihood="pattern", prior_a=1.0, prior_b=1.0)
    pruned, full = _pruned_and_all(**options)
    pairs = slice(4, 7)
    assert pruned.active[0, 0].tolist() == [True] * 4 + [False] * 3
    assert full.active[0, 0].all()

    def fire(learners, readings, reward):
        for learner in learners:
            learner.update_running_mean(
                torch.tensor([readings], dtype=torch.bool),
                torch.tensor([0]),
                torch.tensor([[reward]]),
            )

    # A single that explains every firing keeps the pairs out even where it is plausible: after
    # x = (1, 0, 0) colliding and x = (0, 0, 0) not, (0,) has odds (1/3 * 1/4) / (1/6) = 1/2 >
    # 1/2.5 over "none" (plausible) and both its patterns agree with themselves
    clean = StructureLearner(1, num_actions=1, num_sensors=3, pairs="pruned", **options)
    fire([clean], [1, 0, 0], -1.0)
    fire([clean], [0, 0, 0], 0.0)
    log_posterior = clean.log_posterior()[0, 0]
    sensor = Fraction(1, 3) * Fraction(1, 4) / Fraction(1, 6)
    assert math.isclose((log_posterior[1] - log_posterior[0]).item(), math.log(sensor))
    assert not clean.active[0, 0, pairs].any()
    # 1, 2: x = (0, 0, 0) collides, then does not: every candidate sees its one pattern with
    # n = 2, s = 1 (1/6): none explains, but no single is plausible (1/3 of "none"): no pair
    fire([pruned, full], [0, 0, 0], -1.0)
    fire([pruned, full], [0, 0, 0], 0.0)
    assert not pruned.active[0, 0, pairs].any()
    assert not pruned.count[0, 0, pairs].any()
    assert torch.isinf(pruned.log_posterior()[0, 0, pairs]).all()
    # 3, 4: x = (1, 0, 0) collides twice. (0,): pattern 1 (1, 1) 1/3, pattern 0 (1, 0) 1/6 =
    # 1/18; "none" (1, 0, 1, 1) 1/20: odds 1/3 * 20/18 = 10/27 < 1/2.5, still not plausible
    fire([pruned, full], [1, 0, 0], -1.0)
    fire([pruned, full], [1, 0, 0], -1.0)
    assert not pruned.active[0, 0, pairs].any()
    # 5: once more. (0,): pattern 1 (1, 1, 1) 1/4, * 1/6 = 1/24; "none" (4 of 5) 1/30: odds
    # 1/3 * 30/24 = 5/12 > 1/2.5: (0,) is plausible and its pairs (0, 1), (0, 2) enter, rebuilt
    # from the five firings; (1,) and (2,) read 0 throughout: 1/3 of "none", so (1, 2) stays out.
    fire([pruned, full], [1, 0, 0], -1.0)
    assert pruned.active[0, 0, pairs].tolist() == [True, True, False]
    log_posterior = pruned.log_posterior()[0, 0]
    sensor = Fraction(1, 3) * Fraction(1, 24) / Fraction(1, 30)
    assert math.isclose((log_posterior[1] - log_posterior[0]).item(), math.log(sensor))
    # (0, 1)'s pattern is x0 + 2 x1: firings 1, 2 in pattern 0, firings 3-5 in pattern 1
    assert pruned.count[0, 0, 4].tolist() == [2.0, 3.0, 0.0, 0.0]
    assert pruned.successes[0, 0, 4].tolist() == [1.0, 3.0, 0.0, 0.0]
    assert pruned.reward_sum[0, 0, 4].tolist() == [-1.0, -3.0, 0.0, 0.0]
    # the counts (and the block's, and the marginals) of every active pair: those of counting
    # every firing, bit for bit; so are their log posteriors
    _assert_active_counts_equal(pruned, full)
    assert torch.equal(log_posterior[:6], full.log_posterior()[0, 0, :6])
    # 6: x = (1, 0, 0), no collision. (0,): pattern 1 (3 of 4) 1/20, * 1/6 = 1/120; "none" (4 of
    # 6) 1/105: odds 1/3 * 105/120 = 7/24 < 1/2.5, not plausible; the pairs of sensor 0 read what
    # (0,) reads (1/100 of its prior mass over 3 pairs): not plausible either, so they leave.
    fire([pruned, full], [1, 0, 0], 0.0)
    assert not pruned.active[0, 0, pairs].any()
    _assert_active_counts_equal(pruned, full)


def _assert_active_counts_equal(pruned: StructureLearner, full: StructureLearner) -> None:
    active = pruned.active
    for prefix in ("", "block_"):
        for name in ("count", "successes", "reward_sum", "log_marginal"):
            mine, theirs = getattr(pruned, prefix + name), getattr(full, prefix + name)
            assert torch.equal(mine[active], theirs[active]), prefix + name


def test_active_pairs_hold_the_counts_of_counting_every_firing_on_random_data():
    # 4 experiments, 3 actuators, 7 sensors: actuator 0 collides on sensor 1, actuator 1 on
    # sensors 2 and 5 together, actuator 2 never; fractional rewards on actuator 2's firings
    # (added one at a time on rebuild). With reopening off, the counts do not depend on the
    # decisions: every active candidate's counts equal those of the learner that counts all.
    generator = torch.Generator().manual_seed(3)
    options = dict(num_actions=3, num_sensors=7, window=9, reopen_factor=1e300)
    options |= dict(bayes_factor=20.0)
    pruned = StructureLearner(4, pairs="pruned", **options)
    full = StructureLearner(4, pairs="all", **options)
    entered = left = 0
    for step in range(120):
        readings = torch.rand(4, 7, generator=generator) < 0.5
        action = torch.randint(0, 3, (4,), generator=generator)
        reward = torch.stack(
            (
                -readings[:, 1].float(),
                -(readings[:, 2] & readings[:, 5]).float(),
                -torch.rand(4, generator=generator) * 0.3,
            ),
            dim=1,
        )
        mask = torch.rand(4, generator=generator) < 0.8
        before = pruned.active.clone()
        for learner in (pruned, full):
            learner.update_running_mean(readings, action, reward, mask)
        entered += int((pruned.active & ~before).sum())
        left += int((before & ~pruned.active).sum())
        active = pruned.active
        for prefix in ("", "block_"):
            for name in ("count", "successes", "reward_sum", "log_marginal"):
                mine, theirs = getattr(pruned, prefix + name), getattr(full, prefix + name)
                assert torch.equal(mine[active], theirs[active]), (step, prefix + name)
    assert entered > 0 and left > 0
    assert int(pruned.active.sum()) < int(full.active.sum())
    # the decisions too (here: the same commitments; actuator 1's pair (2, 5) is found and
    # stays active wherever it is committed to)
    assert torch.equal(pruned.committed, full.committed)
    pair = candidate_sets(7).index((2, 5))
    assert (pruned.committed[:, 1] == pair).any()
    assert pruned.active[:, 1, pair][pruned.committed[:, 1] == pair].all()


def test_rebuild_pair_counts_by_hand():
    from factorq_torch.functional import rebuild_pair_counts

    # firings: sensors 0 and 2 read (1, 1), (0, 1), (1, 1); rewards -1, 0, -0.5; the last two in
    # the block. Pair (0, 2): patterns 3, 2, 3.
    readings = torch.tensor([0b101, 0b100, 0b111])
    reward = torch.tensor([-1.0, 0.0, -0.5], dtype=torch.float64)
    block = torch.tensor([False, True, True])
    sums = rebuild_pair_counts(readings, reward, block, torch.tensor([0]), torch.tensor([2]))
    count, successes, reward_sum, block_count, block_successes, block_reward_sum = sums
    assert count.tolist() == [[0.0, 0.0, 1.0, 2.0]]
    assert successes.tolist() == [[0.0, 0.0, 0.0, 1.5]]
    assert reward_sum.tolist() == [[0.0, 0.0, 0.0, -1.5]]
    assert block_count.tolist() == [[0.0, 0.0, 1.0, 1.0]]
    assert block_successes.tolist() == [[0.0, 0.0, 0.0, 0.5]]
    assert block_reward_sum.tolist() == [[0.0, 0.0, 0.0, -0.5]]


def test_pair_activity_and_the_initial_active_set():
    from factorq_torch.functional import (
        initial_activity,
        pair_activity,
        pair_members,
        single_explains,
    )

    sets = candidate_sets(3)
    members = pair_members(sets)
    assert members.tolist() == [[0, 1, 2, 3, 1, 1, 2], [0, 1, 2, 3, 2, 3, 3]]
    small = torch.tensor([True] * 4 + [False] * 3)
    # before any data "no sensor" explains every firing: no pair
    assert initial_activity(sets).tolist() == [True] * 4 + [False] * 3
    inf = -math.inf
    # (1,) plausible: (0, 1) and (1, 2) enter; (0, 2) is plausible itself; nothing committed
    log_posterior = torch.tensor([[0.0, -5.0, -1.0, -5.0, inf, -0.5, inf]], dtype=torch.float64)
    got = pair_activity(log_posterior, torch.tensor([-1]), members, small, math.log(4.0))
    assert got.tolist() == [[True] * 7]
    # nothing plausible but "none" and (1,) ... and (1, 2) committed: (0, 2) leaves
    log_posterior[0, 5] = -3.0
    got = pair_activity(log_posterior, torch.tensor([6]), members, small, 1.0)
    assert got.tolist() == [[True] * 4 + [True, False, True]]
    # while a candidate of at most one sensor explains every firing only the committed pair stays
    got = pair_activity(log_posterior, torch.tensor([6]), members, small, 1.0, torch.tensor([True]))
    assert got.tolist() == [[True] * 4 + [False, False, True]]
    # single_explains by hand: (0,) pure in the first row, nothing of size <= 1 in the second
    count = torch.zeros(2, 7, 4)
    successes = torch.zeros(2, 7, 4)
    count[:, :4, 0], successes[:, :4, 0] = 2.0, 1.0  # every small candidate: pattern 0 mixed
    count[0, 1] = torch.tensor([1.0, 1.0, 0.0, 0.0])
    successes[0, 1] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    assert single_explains(count, successes, small.nonzero().flatten()).tolist() == [True, False]


def test_an_unknown_pair_mode_is_refused_by_name():
    with pytest.raises(ValueError, match="pairs"):
        StructureLearner(1, num_actions=1, num_sensors=3, pairs="some")


@pytest.mark.parametrize("pairs", ["all", "pruned"])
@pytest.mark.parametrize("prediction", ["optimistic", "committed"])
def test_a_few_experiments_on_the_cpu_are_read_as_the_tensor_ops_read_them(prediction, pairs):
    """``local_values`` of a small CPU learner reads its caches as Python numbers
    (``_local_values_read``): bit for bit the tensor path, open, committed and after a reopening."""
    generator = torch.Generator().manual_seed(26)
    learner = StructureLearner(
        3, num_actions=4, num_sensors=4, prediction=prediction, window=30, pairs=pairs
    )
    for step in range(400):
        readings = torch.rand(3, 4, generator=generator) < 0.5
        action = torch.randint(0, 4, (3,), generator=generator)
        parents = readings if step < 200 else readings.roll(1, dims=1)  # the body changes
        reward = -parents.float() * torch.nn.functional.one_hot(action, 4).float()
        learner.update_running_mean(readings, action, reward)
        probe = torch.rand(3, 4, generator=generator) < 0.5
        read, computed = learner._local_values_read(probe), learner._local_values_tensor(probe)
        assert torch.equal(read.view(torch.int32), computed.view(torch.int32)), step
    assert learner.is_committed().all() and int(learner.reopened.sum()) > 0


def test_the_read_path_follows_every_change_of_the_learner():
    """``_local_values_read`` reads the caches through memoryviews of the buffers: what they hold
    after any write (the read update, the tensor update, a reopening, a reset, a loaded state,
    an in-place edit), bit for bit the tensor path's values; a buffer replaced (another tensor)
    is read from the new one."""
    generator = torch.Generator().manual_seed(7)
    learner = StructureLearner(2, num_actions=4, num_sensors=4, window=20)
    other = StructureLearner(2, num_actions=4, num_sensors=4, window=20)
    everyone = torch.ones(2, dtype=torch.bool)

    def check() -> None:
        probe = torch.rand(2, 4, generator=generator) < 0.5
        read, computed = learner.local_values(probe), learner._local_values_tensor(probe)
        assert torch.equal(read.view(torch.int32), computed.view(torch.int32))

    for step in range(300):
        readings = torch.rand(2, 4, generator=generator) < 0.5
        action = torch.randint(0, 4, (2,), generator=generator)
        parents = readings if step < 120 else readings.roll(1, dims=1)  # the body changes
        reward = -parents.float() * torch.nn.functional.one_hot(action, 4).float()
        mask = everyone if step % 3 == 0 else None  # every third firing by the tensor ops
        learner.update_running_mean(readings, action, reward, mask=mask)
        other.update_running_mean(readings.roll(1, dims=1), action, reward)
        check()
        if step == 150:
            learner.load_state_dict(other.state_dict())
        elif step == 200:
            learner.reset(torch.tensor([True, False]))
        elif step == 250:
            learner.mean.mul_(0.5)
        elif step == 260:
            learner.mean = learner.mean.clone()  # another tensor: the views are taken again
        else:
            continue
        check()
    assert int(learner.reopened.sum()) > 0


@pytest.mark.parametrize(
    ("likelihood", "reopen", "experiments", "fractional", "prior"),
    [
        ("mixture", "body", 1, False, 0.25),
        ("mixture", "actuator", 3, True, 0.25),
        ("mixture", "body", 1, False, 0.3),
        ("pattern", "body", 3, False, 0.25),
        ("pattern", "actuator", 1, True, 0.25),
    ],
)
def test_the_online_update_read_as_numbers_is_the_tensor_update_bit_for_bit(
    likelihood, reopen, experiments, fractional, prior
):
    """``update_running_mean`` of one firing per experiment on a small CPU learner takes the
    read path (``_update_read``): every buffer equal, bit for bit, to the tensor path's (run
    here through a mask of all experiments) after every firing, through commitments, noisy
    readings (the noise gate), fractional rewards and reopenings; ``lgamma`` from its tables
    (integral counts, dyadic priors) and from ``torch.lgamma`` (fractional rewards, a prior of
    0.3)."""
    generator = torch.Generator().manual_seed(42)
    options = dict(num_actions=4, num_sensors=4, window=30, likelihood=likelihood, reopen=reopen)
    options.update(prior_a=prior, prior_b=prior)
    read = StructureLearner(experiments, **options)
    tensor = StructureLearner(experiments, **options)
    everyone = torch.ones(experiments, dtype=torch.bool)
    taken = 0
    original = StructureLearner._update_read

    def counted(self, *args):
        nonlocal taken
        done = original(self, *args)
        taken += done
        return done

    for step in range(500):
        readings = torch.rand(experiments, 4, generator=generator) < 0.5
        action = torch.randint(0, 4, (experiments,), generator=generator)
        parents = readings if step < 250 else readings.roll(1, dims=1)  # the body changes
        flips = torch.rand(experiments, 4, generator=generator) < 0.05  # sensors read wrong
        hit = (parents ^ flips).float() * (2.0 / 3.0 if fractional else 1.0)
        reward = -hit * torch.nn.functional.one_hot(action, 4).float()
        StructureLearner._update_read = counted
        try:
            read.update_running_mean(readings, action, reward)
        finally:
            StructureLearner._update_read = original
        tensor.update_running_mean(readings, action, reward, mask=everyone)
        if step % 5 and step < 495:  # every 5th firing and the last ones (a difference stays)
            continue
        for (name, got), value in zip(read.named_buffers(), tensor.buffers(), strict=True):
            assert got.dtype == value.dtype and torch.equal(got, value), (step, name)
            if value.is_floating_point():  # -0.0 and 0.0, NaN payloads: the bits themselves
                width = {torch.float64: torch.int64, torch.float32: torch.int32}[value.dtype]
                assert torch.equal(got.view(width), value.view(width)), (step, name)
    assert taken == 500
    assert int(read.reopened.sum()) > 0 and bool(read.is_committed().any())
    assert bool(read.noise_seen.any())


def test_the_read_update_of_one_experiment_is_the_tensor_update_bit_for_bit_past_the_tables(
    monkeypatch,
):
    """The read update of one experiment (``_update_one``: one agent's step) with its log
    marginals computed entry by entry from the ``lgamma`` tables (``_tabled_log_marginals``)
    and its change-point test of one committed actuator
    (``_change_read``): every buffer equal, bit for bit, to the tensor path's over a stream whose
    counts outgrow the first tables (rebuilt larger), with commitments, noisy readings, closed
    blocks and a reopening."""
    generator = torch.Generator().manual_seed(7)
    options = dict(num_actions=2, num_sensors=4, window=40)
    read, tensor = StructureLearner(1, **options), StructureLearner(1, **options)
    everyone = torch.ones(1, dtype=torch.bool)
    calls = {"_update_one": 0, "_tabled_log_marginals": 0, "_change_read": 0}
    for name in calls:
        function = getattr(StructureLearner, name)  # (a static method: its function)

        def counted(*args, name=name, function=function):
            calls[name] += 1
            return function(*args)

        wrapper = staticmethod(counted) if name == "_tabled_log_marginals" else counted
        monkeypatch.setattr(StructureLearner, name, wrapper)  # (undone after the test)
    for step in range(800):
        readings = torch.rand(1, 4, generator=generator) < 0.5
        action = torch.randint(0, 2, (1,), generator=generator)
        parents = readings if step < 600 else readings.roll(1, dims=1)  # the body changes
        flips = torch.rand(1, 4, generator=generator) < 0.03  # sensors read wrong
        fired = torch.nn.functional.one_hot(action, 2).float()
        reward = -(parents[:, :2] ^ flips[:, :2]).float() * fired  # two actuators, four sensors
        read.update_running_mean(readings, action, reward)
        tensor.update_running_mean(readings, action, reward, mask=everyone)
        if step % 50 and step < 795:
            continue
        for (name, got), value in zip(read.named_buffers(), tensor.buffers(), strict=True):
            assert got.dtype == value.dtype and torch.equal(got, value), (step, name)
            if value.is_floating_point():
                width = {torch.float64: torch.int64, torch.float32: torch.int32}[value.dtype]
                assert torch.equal(got.view(width), value.view(width)), (step, name)
        assert torch.equal(
            read.local_values(readings).view(torch.int32),
            tensor._local_values_tensor(readings).view(torch.int32),
        )
    assert calls["_update_one"] == 800 and calls["_change_read"] > 100
    assert calls["_tabled_log_marginals"] > 1000
    assert read.__dict__["_lgamma_tables"]["size"] > 256  # the tables were rebuilt larger
    assert int(read.reopened.sum()) > 0 and bool(read.noise_seen.any())
