"""The structure learner on the compiled path (issue 12): the kernel's learner equals
``factorq_torch.structure.StructureLearner`` on the modular torchrl path bit for bit (tables,
counts, log marginals, commitments, reopenings, episode metrics and the experiment's structure
bookkeeping) on randomly drawn configurations of every setting of ``factorq dependencies``."""

from __future__ import annotations

import dataclasses
import random

import pytest
import torch

from factorq_torch.functional import beta_bernoulli_log_marginal, lgamma_tables
from factorq_trainers.commands.dependencies.config import SETTINGS, DependenciesConfig
from factorq_trainers.commands.dependencies.methods import run_learned_fast, run_learned_modular
from factorq_trainers.compiled import fast

pytestmark = pytest.mark.skipif(
    not fast.is_available(), reason=f"fast path unavailable: {fast.unavailable_reason()}"
)


def assert_same(fast_result: dict, modular_result: dict) -> None:
    for name, value in modular_result["metrics"].items():
        assert torch.equal(fast_result["metrics"][name], value), name
    for name, value in modular_result["_state"].items():
        assert torch.equal(fast_result["_state"][name], value), name
    for name in ("samples_until_right", "wrong_commitments", "hamming_at_end", "reopened"):
        assert fast_result[name] == modular_result[name], name
    assert torch.equal(fast_result["_curve"], modular_result["_curve"])


def draw_config(setting: str, generator: random.Random) -> DependenciesConfig:
    runs = generator.choice([2, 3])
    return DependenciesConfig(
        seeds=2,
        settings=(setting,),
        runs=runs,
        size=generator.choice([4, 5]),
        obstacles=generator.choice([1, 2]),
        max_steps=generator.choice([60, 100]),
        bayes_factor=generator.choice([3.0, 100.0]),
        max_parents=generator.choice([1, 2]),
        window=generator.choice([7, 20]),
        change_run=1,
        prediction=generator.choice(["optimistic", "map", "committed"]),
        reopen=generator.choice(["body", "actuator"]),
        prior_a=generator.choice([1.0, 0.25, 0.0625, 2.5]),
        prior_b=generator.choice([1.0, 0.25, 1 / 1024]),
        candidate_prior=generator.choice(["size", "sparse", "uniform"]),
        reopen_factor=generator.choice([None, 5.0, 1000.0]),
        likelihood=generator.choice(["mixture", "flip", "pattern"]),
        pairs=generator.choice(["pruned", "all"]),
        noisy_reopen_factor=generator.choice([None, 2.0, 1e4]),
        out="unused",
    )


@pytest.mark.parametrize("setting", list(SETTINGS))
def test_kernel_learner_equals_the_modular_learner_on_random_configurations(setting):
    config = draw_config(setting, random.Random(setting))
    fast_result = run_learned_fast(config, setting)
    assert_same(fast_result, run_learned_modular(config, setting))
    assert sum(fast_result["samples_per_actuator"][0]) > 0


@pytest.mark.parametrize("setting", ["heading", "ring-12-noise-10"])
def test_kernel_learner_equals_the_modular_learner_with_pruned_pairs(setting):
    # pairs on (max_parents 2), pruned: pairs enter (rebuilt from the history) and leave on
    # both paths alike; the active flags and the history's length are compared too
    config = dataclasses.replace(
        draw_config(setting, random.Random("pruned " + setting)),
        max_parents=2,
        pairs="pruned",
        bayes_factor=100.0,
    )
    fast_result = run_learned_fast(config, setting)
    assert_same(fast_result, run_learned_modular(config, setting))
    active = fast_result["_state"]["active"]
    if setting != "heading":  # (its turning actuators never collide: every sensor plausible)
        assert int(active.sum()) < active.numel()  # some pairs out


#: A configuration in which actuators commit, the change reopens them and they commit again
#: (seed 6, since the sensor orders are seeded by the setting's content: two of the four
#: experiments reopen, three with an eager reopen factor).
REOPENING = dict(
    seeds=4,
    seed=6,
    settings=("change",),
    runs=3,
    size=4,
    obstacles=2,
    max_steps=150,
    change_run=1,
    window=20,
    out="unused",
)


def test_kernel_learner_equals_the_modular_learner_through_commitments_and_reopenings():
    # chosen (on the fast path) so that actuators commit, the change reopens them, and they commit
    # again: every branch of the learner runs (REOPENING)
    config = DependenciesConfig(**REOPENING, prediction="optimistic")
    fast_result = run_learned_fast(config, "change")
    assert sum(fast_result["reopened"]) > 0
    assert int((fast_result["_state"]["committed"] >= 0).sum()) > 0
    assert_same(fast_result, run_learned_modular(config, "change"))
    # the change-point test has its own threshold: the same one given explicitly changes nothing,
    # a higher one reopens less (here never), on both paths alike
    same = dataclasses.replace(config, reopen_factor=config.bayes_factor)
    assert run_learned_fast(same, "change")["reopened"] == fast_result["reopened"]
    deaf = dataclasses.replace(config, reopen_factor=1e300)
    deaf_result = run_learned_fast(deaf, "change")
    assert sum(deaf_result["reopened"]) == 0
    assert_same(deaf_result, run_learned_modular(deaf, "change"))
    eager = dataclasses.replace(config, reopen_factor=2.0)
    eager_result = run_learned_fast(eager, "change")
    assert sum(eager_result["reopened"]) > sum(fast_result["reopened"])
    assert_same(eager_result, run_learned_modular(eager, "change"))


def test_lgamma_tables_are_torch_lgamma_of_the_marginals_arguments():
    tables = lgamma_tables(1.0, 0.5, 50)
    count = torch.arange(50, dtype=torch.float64)
    successes = (count // 3).to(torch.float64)
    expected = beta_bernoulli_log_marginal(count, successes, 1.0, 0.5)
    n, s = count.long(), successes.long()
    import math

    constant = math.lgamma(1.0) + math.lgamma(0.5) - math.lgamma(1.5)
    looked_up = tables[0, s] + tables[1, n - s] - tables[2, n] - constant
    assert torch.equal(looked_up, expected)


def test_structure_options_are_checked():
    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import derive_keys

    world = WorldConfig(size=4, num_obstacles=1)
    arguments = ("factor-q", torch.zeros(2, dtype=torch.int64), world, AgentConfig(), 2, 1)
    keys = (derive_keys(0, 0, 2), derive_keys(0, 1, 2))
    orders = torch.arange(4).expand(2, 4).contiguous()
    with pytest.raises(ValueError, match="prediction"):
        fast.ExperimentBatch(
            *arguments, *keys, structure=fast.StructureOptions(orders, prediction="posterior")
        )
    with pytest.raises(ValueError, match="prior_a"):
        fast.ExperimentBatch(
            *arguments, *keys, structure=fast.StructureOptions(orders, prior_a=0.3)
        )
    with pytest.raises(ValueError, match="orders"):
        fast.ExperimentBatch(
            *arguments, *keys, structure=fast.StructureOptions(torch.zeros(2, 4, dtype=torch.int64))
        )
    with pytest.raises(ValueError, match="bayes_factor"):
        fast.ExperimentBatch(
            *arguments, *keys, structure=fast.StructureOptions(orders, bayes_factor=1)
        )
    with pytest.raises(ValueError, match="reopen_factor"):
        fast.ExperimentBatch(
            *arguments, *keys, structure=fast.StructureOptions(orders, reopen_factor=1.0)
        )
    with pytest.raises(ValueError, match="factor-q"):
        fast.ExperimentBatch(
            "q-learning", *arguments[1:], *keys, structure=fast.StructureOptions(orders)
        )


def test_sensor_orders_relabel_the_joint_table_and_q_learning_and_change_at_the_run():
    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import derive_keys

    world = WorldConfig(size=4, num_obstacles=2)
    count = 3
    arguments = (torch.zeros(count, dtype=torch.int64), world, AgentConfig(), 4, 1)
    keys = (derive_keys(0, 1, count), derive_keys(0, 2, count))
    generator = torch.Generator().manual_seed(0)
    orders = torch.stack([torch.randperm(4, generator=generator) for _ in range(count)])
    after = torch.stack([torch.randperm(4, generator=generator) for _ in range(count)])
    joint = torch.ones(4, 4, dtype=torch.bool)
    for algorithm, dependency in (("q-learning", None), ("factor-q", joint)):

        def run(sensor_orders=None, algorithm=algorithm, dependency=dependency):
            return fast.run_experiments(
                algorithm, *arguments, *keys, dependency=dependency, sensor_orders=sensor_orders
            )

        plain = run()
        # a fixed order relabels the table entries: the same numbers
        for same in (fast.SensorOrders(orders), fast.SensorOrders(orders, orders, 2)):
            got = run(same)
            assert all(torch.equal(got[name], plain[name]) for name in plain), algorithm
        changed = run(fast.SensorOrders(orders, after, 2))
        # runs before the change are untouched; Q-learning's table restarts at every run, so
        # only the first step of run 2 (the observation still in the old order) can differ
        for name in plain:
            assert torch.equal(changed[name][:, :2], plain[name][:, :2]), name
        if dependency is not None:  # the joint table outlives the change: it matters
            assert not torch.equal(changed["steps"], plain["steps"])
    with pytest.raises(ValueError, match="sensor_orders"):
        fast.ExperimentBatch(
            "factor-q",
            *arguments,
            *keys,
            structure=fast.StructureOptions(orders),
            sensor_orders=fast.SensorOrders(orders),
        )


@pytest.mark.parametrize("likelihood", ["flip", "pattern"])
def test_every_likelihood_reopens_alike_on_both_paths(likelihood):
    # the change-point test reads each likelihood's own marginals (the flip likelihood's whole
    # candidate, the others' patterns): the configuration above reopens under each of them
    config = DependenciesConfig(**REOPENING, likelihood=likelihood)
    fast_result = run_learned_fast(config, "change")
    assert sum(fast_result["reopened"]) > 0
    assert_same(fast_result, run_learned_modular(config, "change"))


def test_the_noise_gate_flags_noisy_sensors_only_and_raises_the_reopening_threshold_alike():
    # noisy_reopen_factor: once a commitment rests on data against a pattern's majority the
    # experiment's sensors read wrong (noise_seen) and the change-point test asks for its own odds.
    # A clean world never sets the flag; a noisy one does, and an eager noisy threshold then
    # reopens more than the default one, on both paths alike
    base = dict(seeds=4, seed=3, runs=3, size=5, obstacles=2, max_steps=150, window=20)
    clean = DependenciesConfig(**base, settings=("cross",), out="unused")
    clean_result = run_learned_fast(clean, "cross")
    assert int((clean_result["_state"]["committed"] >= 0).sum()) > 0
    assert int(clean_result["_state"]["noise_seen"].sum()) == 0
    noisy = DependenciesConfig(
        **base, settings=("noise-10",), noisy_reopen_factor=None, out="unused"
    )
    default = run_learned_fast(noisy, "noise-10")
    assert int(default["_state"]["noise_seen"].sum()) > 0
    eager = dataclasses.replace(noisy, noisy_reopen_factor=1.01)
    eager_result = run_learned_fast(eager, "noise-10")
    assert sum(eager_result["reopened"]) > sum(default["reopened"])
    assert_same(eager_result, run_learned_modular(eager, "noise-10"))


@pytest.mark.parametrize("setting", ["heading", "noise-10"])
def test_kernel_learner_equals_the_modular_learner_with_the_risk_options(setting):
    # the learner as the local provider under the risk gate and risk-aware exploration (issue 39)
    config = dataclasses.replace(
        draw_config(setting, random.Random("risk " + setting)),
        risk_gate="on",
        exploration="risk-aware",
    )
    fast_result = run_learned_fast(config, setting)
    assert_same(fast_result, run_learned_modular(config, setting))
