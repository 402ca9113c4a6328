"""Epsilon-greedy policies: per-experiment counter streams, random ties, eqs. 2-3, bad input."""

from __future__ import annotations

import pytest
import reference  # tests/reference.py: pytest puts tests/ on sys.path (no __init__.py)
import torch
from tensordict import TensorDict

from factorq_torch.base.rng import MASK64, STREAM_POLICY, derive_keys
from factorq_torch.policy import MASK_KEY, EpsilonGreedyPolicy, FactorQPolicy


def values_td(values: torch.Tensor, **entries) -> TensorDict:
    return TensorDict(action_value=values, **entries, batch_size=[values.shape[0]])


def test_the_t_th_decision_draws_the_reference_streams_counters():
    # The same keys and counters as tests/reference.py `select`, over 50 decisions of 3
    # experiments with ties and a high epsilon.
    policy = EpsilonGreedyPolicy(3, seed=5, epsilon=0.3)
    keys = derive_keys(5, STREAM_POLICY, 3)
    values = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 2.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    for t in range(50):
        td = policy(values_td(values))
        for i in range(3):
            action, exploratory = reference.select(
                values[i].tolist(), 0.3, int(keys[i]) & MASK64, t
            )
            assert (td["action"][i].item(), td["exploratory"][i].item()) == (action, exploratory)
    assert policy.counter.tolist() == [50, 50, 50]


def test_an_experiment_draws_the_same_alone_as_in_a_batch():
    values = torch.zeros(4, 4)
    batch = EpsilonGreedyPolicy(4, seed=9, epsilon=0.5)
    alone = EpsilonGreedyPolicy(1, seed=9, epsilon=0.5, offset=2)
    for _ in range(20):
        in_batch = batch(values_td(values))
        single = alone(values_td(values[:1]))
        assert in_batch["action"][2] == single["action"][0]
        assert in_batch["exploratory"][2] == single["exploratory"][0]


def test_masked_experiments_draw_nothing_and_keep_their_counter():
    policy = EpsilonGreedyPolicy(2, seed=0)
    mask = torch.tensor([True, False])
    policy(values_td(torch.zeros(2, 4)))
    policy(values_td(torch.zeros(2, 4), collector=TensorDict({"mask": mask}, [2])))
    assert policy.counter.tolist() == [2, 1]
    assert MASK_KEY == ("collector", "mask")


def test_ties_on_an_all_zero_table_are_broken_uniformly():
    policy = EpsilonGreedyPolicy(4000, seed=1, epsilon=0.0)
    actions = policy(values_td(torch.zeros(4000, 4)))["action"]
    counts = torch.bincount(actions, minlength=4)
    # Binomial(4000, 1/4): mean 1000, sd sqrt(4000 * 3/16) = 27.4; 5 sd = 137
    assert ((counts - 1000).abs() < 137).all(), counts


def test_factorq_policy_writes_combined_values_of_eqs_2_and_3_and_takes_their_argmax():
    policy = FactorQPolicy(1, epsilon=0.0)
    td = TensorDict(
        action_value=torch.tensor([[2.0, 0.0, 0.0, 1.0]]),  # x = 2 - 1/3 = 5/3
        local_value=torch.tensor([[-1.0, 0.0, 0.0, 0.0]]),  # y = 1: G = 5/3 * 1.1 = 11/6
        batch_size=[1],
    )
    td = policy(td)
    # C = [2 - 11/6, 0, 0, 1] = [1/6, 0, 0, 1]: the local term turns the greedy choice to east
    assert torch.allclose(td["combined_value"], torch.tensor([[1 / 6, 0.0, 0.0, 1.0]]))
    assert td["action"].item() == 3 and not td["exploratory"].item()


def test_factorq_policy_avoids_a_sensed_obstacle_in_an_unvisited_state():
    # All Q equal: G falls to g_min and rho alone decides; ties among the free moves are random.
    policy = FactorQPolicy(2000, seed=3, epsilon=0.0)
    td = TensorDict(
        action_value=torch.zeros(2000, 4),
        local_value=torch.tensor([[-1.0, 0.0, 0.0, 0.0]]).expand(2000, 4),
        batch_size=[2000],
    )
    counts = torch.bincount(policy(td)["action"], minlength=4)
    assert counts[0] == 0 and (counts[1:] > 550).all(), counts  # ~667 each of 1, 2, 3


def test_policy_streams_round_trip_through_state_dict_and_set_seed_rewinds_them():
    policy = EpsilonGreedyPolicy(3, seed=4, epsilon=0.5)
    other = EpsilonGreedyPolicy(3, seed=0, epsilon=0.5)  # other streams until loaded
    values = torch.zeros(3, 4)
    policy(values_td(values))
    other.load_state_dict(policy.state_dict())
    assert torch.equal(policy(values_td(values))["action"], other(values_td(values))["action"])
    first = EpsilonGreedyPolicy(3, seed=4, epsilon=0.5)(values_td(values))["action"]
    policy.set_seed(4)
    assert policy.counter.tolist() == [0, 0, 0]
    assert torch.equal(policy(values_td(values))["action"], first)


# -- bad input ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"epsilon": 1.5}, "epsilon=1.5 is out of range"),
        ({"epsilon": -0.1}, "epsilon=-0.1 is out of range"),
        ({"eta": -1.0}, "eta=-1.0 is out of range"),
        ({"g_min": 0.0}, "g_min=0.0 is out of range"),
    ],
)
def test_hyperparameters_out_of_range_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FactorQPolicy(2, **kwargs)


def test_misshapen_values_and_mismatched_batches_are_refused():
    policy = FactorQPolicy(2)
    with pytest.raises(ValueError, match="S=2 experiments .* batch_size \\[3\\]"):
        policy(values_td(torch.zeros(3, 4), local_value=torch.zeros(3, 4)))
    with pytest.raises(ValueError, match="'action_value' has shape \\[2\\]"):
        policy(values_td(torch.zeros(2), local_value=torch.zeros(2, 4)))
    with pytest.raises(ValueError, match="local_value has shape \\[2, 3\\]"):
        policy(values_td(torch.zeros(2, 4), local_value=torch.zeros(2, 3)))
    with pytest.raises(KeyError, match="needs 'local_value'"):
        policy(values_td(torch.zeros(2, 4)))
    with pytest.raises(ValueError, match="keys has shape \\[3\\], expected \\[2\\]"):
        EpsilonGreedyPolicy(2, keys=torch.zeros(3, dtype=torch.int64))


def test_risk_aware_exploration_never_explores_into_a_risky_actuator():
    # epsilon 1: every action explores; actuators 0 and 2 are risky (rho < -0.5)
    policy = FactorQPolicy(4, seed=3, epsilon=1.0, exploration="risk-aware")
    rho = torch.tensor([[-1.0, 0.0, -0.75, -0.5]] * 4)
    seen = set()
    for _ in range(50):
        td = policy(values_td(torch.zeros(4, 4), local_value=rho))
        assert bool(td["exploratory"].all())
        seen.update(td["action"].tolist())
    assert seen == {1, 3}


def test_risk_aware_exploration_falls_back_to_every_actuator_when_all_are_risky():
    policy = FactorQPolicy(4, seed=3, epsilon=1.0, exploration="risk-aware")
    seen = set()
    for _ in range(50):
        td = policy(values_td(torch.zeros(4, 4), local_value=torch.full((4, 4), -1.0)))
        seen.update(td["action"].tolist())
    assert seen == {0, 1, 2, 3}


def test_the_risk_gate_lets_the_task_value_choose_under_a_small_risk():
    values = torch.tensor([[1.0, 0.0, 0.0]])
    rho = torch.tensor([[-0.02, 0.0, 0.0]])
    paper = FactorQPolicy(1, epsilon=0.0)(values_td(values, local_value=rho))
    gated = FactorQPolicy(1, epsilon=0.0, risk_gate=True)(values_td(values, local_value=rho))
    assert paper["action"].item() in (1, 2)  # eq. 3 turns on the spot
    assert gated["action"].item() == 0
    assert torch.equal(gated["combined_value"], values)  # G = g_min times zeros


def test_risk_aware_exploration_is_refused_where_no_local_value_is_read():
    with pytest.raises(ValueError, match=r"exploration='risk-aware'.*EpsilonGreedyPolicy"):
        EpsilonGreedyPolicy(1, exploration="risk-aware")
    with pytest.raises(ValueError, match="exploration='careful' is unknown"):
        FactorQPolicy(1, exploration="careful")
