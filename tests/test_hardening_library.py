"""Issue 29 item 6: the library refuses non-finite rewards, out-of-range indices and seeds past
the documented range where they enter, naming the key, the value and the first experiment."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from factorq_envs import FactoredGridEnv
from factorq_torch.base.validation import INT64_MAX, check_finite, check_indices
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.policy import FactorQPolicy
from factorq_torch.structure import StructureLearner
from factorq_torch.tables import LocalRewardTable, TaskQTable

S, CELLS = 3, 4


def step(reward=None, local_reward=None, action=None, cell=None, sensors=None) -> TensorDict:
    """One online transition of S experiments (valid unless an argument says otherwise)."""
    local = torch.zeros(S, 4) if local_reward is None else torch.as_tensor(local_reward)
    return TensorDict(
        {
            "cell": torch.tensor([0, 1, 2]) if cell is None else torch.as_tensor(cell),
            "sensors": torch.zeros(S, 4, dtype=torch.bool) if sensors is None else sensors,
            "action": torch.tensor([0, 1, 2]) if action is None else torch.as_tensor(action),
            "next": TensorDict(
                {
                    "cell": torch.tensor([1, 2, 3]),
                    "sensors": torch.zeros(S, 4, dtype=torch.bool),
                    "reward": torch.full((S, 1), -1.0) if reward is None else reward,
                    "local_reward": local.to(torch.float32),
                    "terminated": torch.zeros(S, 1, dtype=torch.bool),
                },
                [S],
            ),
        },
        batch_size=[S],
    )


def factorq_loss() -> FactorQLoss:
    return FactorQLoss(TaskQTable(S, CELLS, sparse_grad=True), LocalRewardTable(S))


def apply(loss, td, how):
    if how == "forward":
        loss(td)
    else:
        loss.tabular_step(td)


@pytest.mark.parametrize("how", ["forward", "tabular_step"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_task_reward_is_refused_naming_the_key_the_experiment_and_the_value(how, bad):
    loss = factorq_loss()
    reward = torch.full((S, 1), -1.0)
    reward[1, 0] = bad
    before = loss.local_value_network.rho.clone()
    with pytest.raises(ValueError) as error:
        apply(loss, step(reward=reward), how)
    message = str(error.value)
    assert "FactorQLoss: ('next', 'reward') holds NaN or infinite values" in message
    assert "(experiment 1 first)" in message and message.endswith(f"(first: {bad})")
    assert torch.equal(loss.local_value_network.rho, before)  # refused before any write


@pytest.mark.parametrize("how", ["forward", "tabular_step"])
def test_a_non_finite_local_reward_is_refused_naming_the_key(how):
    local = torch.zeros(S, 4)
    local[2, 3] = -math.inf
    with pytest.raises(ValueError, match=r"'local_reward'\) holds NaN .*experiment 2 first"):
        apply(factorq_loss(), step(local_reward=local), how)


@pytest.mark.parametrize("how", ["forward", "tabular_step"])
@pytest.mark.parametrize("action", [[0, 4, 1], [0, 1, -1]])
def test_an_action_out_of_range_is_one_line_naming_the_experiment_and_the_value(how, action):
    with pytest.raises(ValueError) as error:
        apply(factorq_loss(), step(action=action), how)
    bad = 1 if action[1] == 4 else 2
    assert str(error.value) == (
        f"FactorQLoss: action holds values outside [0, 4) (experiment {bad} first): {action[bad]}"
    )


def test_the_q_learning_loss_refuses_a_nan_reward_too():
    loss = TabularQLoss(TaskQTable(S, CELLS, sparse_grad=True))
    reward = torch.full((S, 1), math.nan)
    with pytest.raises(ValueError, match=r"TabularQLoss: \('next', 'reward'\) holds NaN"):
        loss.tabular_step(step(reward=reward))


def test_a_reward_on_another_device_names_the_key():
    reward = torch.full((S, 1), -1.0, device="meta")
    td = step()
    td.get("next").set("reward", reward)  # tensordict without a device holds mixed devices
    with pytest.raises(
        ValueError, match=r"\('next', 'reward'\) is on meta but the tables are on cpu"
    ):
        factorq_loss()(td)


def test_a_negative_cell_is_reported_as_it_is():
    with pytest.raises(ValueError) as error:
        factorq_loss().tabular_step(step(cell=[0, -3, 1]))
    assert (
        "'cell' holds cell -3 (transition 1 first): a table of num_cells=4 holds cells 0 to 3"
        in str(error.value)
    )
    with pytest.raises(ValueError, match=r"num_cells=4 but received cell 9 \(transition 2 first\)"):
        TaskQTable(S, CELLS)(TensorDict(cell=torch.tensor([0, 1, 9]), batch_size=[S]))


def test_the_local_table_refuses_what_its_update_cannot_use():
    table = LocalRewardTable(S)
    readings, action = torch.zeros(S, 4, dtype=torch.bool), torch.tensor([0, 1, 2])
    with pytest.raises(ValueError, match=r"action holds values outside \[0, 4\) .*: 7"):
        table.update_running_mean(readings, torch.tensor([0, 7, 1]), torch.zeros(S, 4))
    with pytest.raises(ValueError, match=r"local_reward holds NaN .*experiment 0 first"):
        table.update_running_mean(readings, action, torch.full((S, 4), math.nan))
    with pytest.raises(TypeError, match="readings must be bool sensor readings, got torch.float32"):
        table.update_running_mean(readings.float(), action, torch.zeros(S, 4))
    assert table.kappa.sum() == 0  # nothing written


@pytest.mark.parametrize("bad", [math.nan, -math.inf])
def test_the_structure_learner_refuses_non_finite_rewards_and_keeps_its_state(bad):
    learner = StructureLearner(S, num_actions=4, num_sensors=4)
    readings, action = torch.zeros(S, 4, dtype=torch.bool), torch.tensor([0, 1, 2])
    reward = torch.zeros(S, 4)
    reward[1, 1] = bad
    count = learner.count.clone()
    with pytest.raises(ValueError, match=r"local_reward holds NaN .*experiment 1 first"):
        learner.update_running_mean(readings, action, reward)
    assert torch.equal(learner.count, count)
    learner.update_running_mean(readings, action, torch.zeros(S, 4))  # still usable
    assert learner.count.sum() > count.sum()


def test_the_structure_learner_refuses_float_readings_and_actions_out_of_range():
    learner = StructureLearner(S, num_actions=4, num_sensors=4)
    readings, reward = torch.zeros(S, 4, dtype=torch.bool), torch.zeros(S, 4)
    with pytest.raises(TypeError, match="readings must be bool sensor readings"):
        learner.update_running_mean(readings.float(), torch.tensor([0, 1, 2]), reward)
    with pytest.raises(ValueError, match=r"action holds values outside \[0, 4\) .*: -1"):
        learner.update_running_mean(readings, torch.tensor([0, -1, 2]), reward)


@pytest.mark.parametrize("seed", [2**80, 2**64, INT64_MAX + 1, -1])
def test_seeds_past_the_documented_range_are_refused(seed):
    with pytest.raises(
        ValueError, match=rf"seed={seed} is out of range: must be in \[0, {INT64_MAX}\]"
    ):
        FactoredGridEnv(batch_size=[1], seed=seed)
    with pytest.raises(ValueError, match="seed="):
        FactorQPolicy(1, seed=seed)
    FactoredGridEnv(batch_size=[1], seed=INT64_MAX)  # the end of the range is fine


def test_the_checks_return_their_input_and_stay_silent_on_good_values():
    values = torch.tensor([[0.5, -1.0], [2.0, 0.0]])
    assert check_finite("owner", "x", values) is values
    index = torch.tensor([0, 3, 2])
    assert check_indices("owner", "x", index, 4) is index
    assert check_indices("owner", "x", index[:0], 0).numel() == 0
    # a sum that overflows is not a bad value: the entries are checked one by one then
    huge = torch.tensor([3e38, 3e38])
    assert check_finite("owner", "x", huge) is huge
