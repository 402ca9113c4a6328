"""FactorQLoss and TabularQLoss: hand-computed updates, the exact SGD form, keys, bad input."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from factorq_torch.functional import (
    combined_values,
    factorq_target,
    normaliser,
    q_learning_target,
    q_update,
    running_mean_update,
)
from factorq_torch.objectives import FactorQLoss, TabularQLoss, tabular_optimizer
from factorq_torch.tables import LocalRewardTable, TaskQTable


def transition(
    cell,
    proximity,
    action,
    next_cell,
    next_proximity,
    reward,
    local_reward=None,
    terminated=None,
    truncated=None,
) -> TensorDict:
    """A transition of S experiments with the env's keys (``[S, 1]`` rewards and flags)."""
    batch = len(cell)
    terminated = torch.zeros(batch, dtype=torch.bool) if terminated is None else terminated
    truncated = torch.zeros(batch, dtype=torch.bool) if truncated is None else truncated
    following = {
        "cell": torch.as_tensor(next_cell),
        "sensors": torch.as_tensor(next_proximity),
        "reward": torch.as_tensor(reward, dtype=torch.float32).reshape(batch, 1),
        "terminated": terminated.reshape(batch, 1),
        "truncated": truncated.reshape(batch, 1),
        "done": (terminated | truncated).reshape(batch, 1),
    }
    if local_reward is not None:
        following["local_reward"] = torch.as_tensor(local_reward, dtype=torch.float32)
    return TensorDict(
        {
            "cell": torch.as_tensor(cell),
            "sensors": torch.as_tensor(proximity),
            "action": torch.as_tensor(action),
            "next": TensorDict(following, [batch]),
        },
        batch_size=[batch],
    )


def hand_example(terminated=False, truncated=False):
    """One Factor-Q step worked out by hand (see the test below for the arithmetic)."""
    task, local = TaskQTable(1, num_cells=4), LocalRewardTable(1)
    with torch.no_grad():
        task.table[0, 0, 2] = 0.5  # Q(s, south)
        task.table[0, 1] = torch.tensor([2.0, 0.0, 1.5, 0.0])  # Q(s')
        local.rho[0, 0, 1], local.kappa[0, 0, 1] = -1.0, 1  # north with the sensor on: -1
        local.rho[0, 2, 0], local.kappa[0, 2, 0] = -0.5, 1  # south with the sensor off: -0.5
    td = transition(
        cell=[0],
        proximity=[[True, True, False, False]],  # s: walls north and west
        action=[2],  # south, free: o_2 = 0
        next_cell=[1],
        next_proximity=[[True, False, False, False]],  # s': wall north
        reward=[0.0 if terminated else -1.0],  # task reward
        local_reward=[[0.0, 0.0, 0.0, 0.0]],
        terminated=torch.tensor([terminated]),
        truncated=torch.tensor([truncated]),
    )
    return task, local, td


@pytest.mark.parametrize("truncated", [False, True])
def test_factorq_loss_applies_eq_4_with_the_local_tables_before_eq_5(truncated):
    task, local, td = hand_example(truncated=truncated)
    loss = FactorQLoss(task, local)
    optimizer = tabular_optimizer(loss)
    out = loss(td)
    out["loss_task"].backward()
    optimizer.step()
    # At s': Q = [2, 0, 1.5, 0], rho = [rho_0[1], rho_1[0], rho_2[0], rho_3[0]] = [-1, 0, -0.5, 0]
    #   x = 2 - 0.5 = 1.5;  P_bar = -1/6, y = 5/6;  G = 1.5 / (5/6) * 1.1 = 1.98
    #   C(s') = [0.02, 0, 0.51, 0];  target = -1 + 0.9 * 0.51 = -0.541 (truncated: the same)
    # (with rho_2[0] already updated to -0.25, C(s')[2] would be 1.05 and the target -0.055)
    # Q(s, south) = 0.5 + 0.2 * (-0.541 - 0.5) = 0.2918;  loss = 0.2 * 0.5 * 1.041**2
    assert task.table[0, 0, 2].item() == pytest.approx(0.2918, abs=1e-6)
    assert out["td_error"].item() == pytest.approx(1.041, abs=1e-6)
    assert out["loss_task"].item() == pytest.approx(0.1 * 1.041**2, abs=1e-6)
    # eq. 5 on south at reading 0: kappa 1 -> 2, rho = -0.5 + (0 + 0.5) / 2 = -0.25
    assert local.kappa[0, 2, 0] == 2 and local.rho[0, 2, 0] == -0.25
    assert out["loss_local"].item() == pytest.approx(0.5 * 0.5**2)  # (rho_2[0] - 0)**2 / 2
    # nothing else moved
    assert task.table[0, 1].tolist() == [2.0, 0.0, 1.5, 0.0] and local.kappa.sum() == 3


def test_factorq_loss_does_not_bootstrap_past_the_goal():
    task, local, td = hand_example(terminated=True)
    loss = FactorQLoss(task, local)
    optimizer = tabular_optimizer(loss)
    loss(td)["loss_task"].backward()
    optimizer.step()
    # target = task reward alone = -1 + 1 = 0;  Q = 0.5 + 0.2 * (0 - 0.5) = 0.4
    assert task.table[0, 0, 2].item() == pytest.approx(0.4)


def test_tabular_q_loss_applies_eq_1_with_the_conventional_reward():
    task = TaskQTable(1, num_cells=2, with_sensors=True)
    proximity = torch.tensor([[True, False, False, False]])  # pattern 1
    with torch.no_grad():
        task.table[0, 0 * 16 + 1, 0] = 0.5  # Q(s, north)
        task.table[0, 0 * 16 + 1] += torch.tensor([0.0, 1.0, 2.0, 3.0])
    td = transition([0], proximity, [0], [0], proximity, reward=[-2.0])  # bumped north
    loss = TabularQLoss(task)
    optimizer = tabular_optimizer(loss)
    loss(td)["loss_task"].backward()
    optimizer.step()
    # s' = s: Q(s') = [0.5, 1, 2, 3] before the update; target = -2 + 0.9 * 3 = 0.7
    # Q(s, north) = 0.5 + 0.2 * (0.7 - 0.5) = 0.54
    assert task.table[0, 1, 0].item() == pytest.approx(0.54)


def random_batch(batch, num_cells, generator, local=True):
    cells = torch.randint(0, num_cells, (2, batch), generator=generator)
    bits = torch.rand(2, batch, 4, generator=generator) < 0.5
    action = torch.randint(0, 4, (batch,), generator=generator)
    collided = bits[0].gather(1, action.unsqueeze(1)).squeeze(1)
    local_reward = -torch.nn.functional.one_hot(action, 4).float() * collided.unsqueeze(1)
    terminated = torch.rand(batch, generator=generator) < 0.2
    return transition(
        cells[0],
        bits[0],
        action,
        cells[1],
        bits[1],
        reward=torch.where(terminated, 0.0, -1.0),
        local_reward=local_reward if local else None,
        terminated=terminated,
    )


def test_one_sgd_step_of_learning_rate_1_on_the_factorq_loss_equals_q_update_bit_for_bit():
    generator = torch.Generator().manual_seed(0)
    batch, num_cells = 256, 6
    task, local = TaskQTable(batch, num_cells), LocalRewardTable(batch)
    with torch.no_grad():
        task.table.copy_(torch.randn(task.table.shape, generator=generator) * 3)
        local.kappa.copy_(torch.randint(0, 9, local.kappa.shape, generator=generator))
        local.rho.copy_(-torch.rand(local.rho.shape, generator=generator) * (local.kappa > 0))
    td = random_batch(batch, num_cells, generator)
    rows, action = torch.arange(batch), td["action"]
    # the expected update, straight from functional
    table, rho, kappa = task.table.detach().clone(), local.rho.clone(), local.kappa.clone()
    q_next = table[rows, td["next", "cell"]]
    rho_next = rho.gather(2, td["next", "sensors"].long().unsqueeze(-1)).squeeze(-1)
    c_next = combined_values(q_next, rho_next, normaliser(q_next, rho_next, 0.3, 0.02))
    reward, terminated = td["next", "reward"].squeeze(-1), td["next", "terminated"].squeeze(-1)
    target = factorq_target(reward, c_next, terminated, gamma=0.8)
    cell = td["cell"]
    table[rows, cell, action] = q_update(table[rows, cell, action], target, alpha=0.3)
    reading = td["sensors"][rows, action].long()
    reward_local = td["next", "local_reward"][rows, action]
    rho[rows, action, reading], kappa[rows, action, reading] = running_mean_update(
        rho[rows, action, reading], kappa[rows, action, reading], reward_local
    )
    loss = FactorQLoss(task, local, gamma=0.8, alpha=0.3, eta=0.3, g_min=0.02)
    optimizer = tabular_optimizer(loss)
    loss(td)["loss_task"].backward()
    optimizer.step()
    assert torch.equal(task.table.detach(), table)
    assert torch.equal(local.rho, rho) and torch.equal(local.kappa, kappa)


def test_one_sgd_step_of_learning_rate_1_on_the_tabular_loss_equals_q_update_bit_for_bit():
    generator = torch.Generator().manual_seed(1)
    batch, num_cells = 256, 3
    task = TaskQTable(batch, num_cells, with_sensors=True)
    with torch.no_grad():
        task.table.copy_(torch.randn(task.table.shape, generator=generator) * 3)
    td = random_batch(batch, num_cells, generator, local=False)
    rows, action = torch.arange(batch), td["action"]
    table = task.table.detach().clone()
    pattern = (td["sensors"].long() * torch.tensor([1, 2, 4, 8])).sum(-1)
    next_pattern = (td["next", "sensors"].long() * torch.tensor([1, 2, 4, 8])).sum(-1)
    state, next_state = td["cell"] * 16 + pattern, td["next", "cell"] * 16 + next_pattern
    reward, terminated = td["next", "reward"].squeeze(-1), td["next", "terminated"].squeeze(-1)
    target = q_learning_target(reward, table[rows, next_state], terminated, gamma=0.9)
    table[rows, state, action] = q_update(table[rows, state, action], target, alpha=0.2)
    loss = TabularQLoss(task)
    optimizer = tabular_optimizer(loss)
    loss(td)["loss_task"].backward()
    optimizer.step()
    assert torch.equal(task.table.detach(), table)


def test_the_loss_does_not_mutate_its_input():
    task, local, td = hand_example()
    before = td.clone()
    FactorQLoss(task, local)(td)
    assert set(td.keys(True, True)) == set(before.keys(True, True))
    assert (td == before).all()


def test_masked_experiments_get_no_gradient_and_keep_their_local_tables():
    task, local, td = hand_example()
    td = torch.cat([td, td])  # two copies of the hand example
    task2, local2 = TaskQTable(2, num_cells=4), LocalRewardTable(2)
    with torch.no_grad():
        task2.table.copy_(task.table.expand(2, -1, -1))
        local2.rho.copy_(local.rho.expand(2, -1, -1))
        local2.kappa.copy_(local.kappa.expand(2, -1, -1))
    td["collector", "mask"] = torch.tensor([True, False])
    loss = FactorQLoss(task2, local2)
    loss(td)["loss_task"].backward()
    assert task2.table.grad[1].abs().sum() == 0 and task2.table.grad[0].abs().sum() > 0
    assert local2.kappa[0, 2, 0] == 2 and local2.kappa[1, 2, 0] == 1


def test_in_eval_mode_the_loss_leaves_the_local_tables_alone():
    task, local, td = hand_example()
    loss = FactorQLoss(task, local).eval()
    loss(td)
    assert local.kappa[0, 2, 0] == 1 and local.rho[0, 2, 0] == -0.5


def test_set_keys_renames_the_entries_the_loss_reads():
    task, local, td = hand_example()
    td["next", "task_reward"] = td["next"].pop("reward")
    loss = FactorQLoss(task, local)
    with pytest.raises(KeyError, match="'reward'"):
        loss(td)
    loss.set_keys(reward="task_reward")
    assert ("next", "task_reward") in loss.in_keys
    assert loss(td)["td_error"].item() == pytest.approx(1.041, abs=1e-6)
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(rewards="task_reward")


def test_a_neural_value_provider_learns_from_the_same_loss_unchanged():
    torch.manual_seed(0)
    task_net = TensorDictModule(
        torch.nn.Linear(4, 4), in_keys=["features"], out_keys=["action_value"]
    )
    local_net = TensorDictModule(
        torch.nn.Linear(4, 4), in_keys=["features"], out_keys=["local_value"]
    )
    _, _, td = hand_example()
    td["features"] = td["sensors"].float()
    td["next", "features"] = td["next", "sensors"].float()
    out = FactorQLoss(task_net, local_net, reduction="mean")(td)
    (out["loss_task"] + out["loss_local"]).backward()
    assert task_net.module.weight.grad.abs().sum() > 0
    assert local_net.module.weight.grad.abs().sum() > 0


def test_mean_reduction_divides_the_sum_by_the_experiments_that_count():
    task, local, td = hand_example()
    td = torch.cat([td, td, td])
    task3, local3 = TaskQTable(3, num_cells=4), LocalRewardTable(3)
    with torch.no_grad():
        task3.table.copy_(task.table.expand(3, -1, -1))
        local3.rho.copy_(local.rho.expand(3, -1, -1))
    td["collector", "mask"] = torch.tensor([True, True, False])
    summed = FactorQLoss(task3, local3).eval()(td)["loss_task"]
    mean = FactorQLoss(task3, local3, reduction="mean").eval()(td)["loss_task"]
    assert summed.item() == pytest.approx(2 * 0.1 * 1.041**2, abs=1e-6)
    assert mean.item() == pytest.approx(summed.item() / 2)


# -- bad input ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"alpha": 0.0}, "alpha=0.0 is out of range"),
        ({"alpha": 1.5}, "alpha=1.5 is out of range"),
        ({"gamma": 1.0}, "gamma=1.0 is out of range"),
        ({"gamma": -0.1}, "gamma=-0.1 is out of range"),
        ({"eta": -0.5}, "eta=-0.5 is out of range"),
        ({"g_min": -1.0}, "g_min=-1.0 is out of range"),
        ({"reduction": "max"}, "reduction='max' is unknown"),
    ],
)
def test_hyperparameters_out_of_range_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FactorQLoss(TaskQTable(1, 4), LocalRewardTable(1), **kwargs)


def test_misshapen_transitions_are_refused_with_the_entry_named():
    task, local, td = hand_example()
    loss = FactorQLoss(task, local)
    bad = td.clone()
    bad["action"] = torch.tensor([[2, 2]])
    with pytest.raises(ValueError, match="'action' has shape \\[1, 2\\], expected \\[1\\]"):
        loss(bad)
    bad = td.clone()
    bad["action"] = torch.tensor([2.0])
    with pytest.raises(ValueError, match="integer action indices"):
        loss(bad)
    bad = td.clone()
    bad["next", "local_reward"] = torch.zeros(1, 3)
    with pytest.raises(ValueError, match="'local_reward'\\) has shape \\[1, 3\\]"):
        loss(bad)
    # one experiment: any batch shape is its transitions (a [1, 1] rollout is one transition)
    loss.eval()
    assert loss(td.unsqueeze(0))["loss_task"] == loss(td)["loss_task"]


def test_a_transition_of_another_batch_size_than_the_tables_is_refused():
    _, _, td = hand_example()
    loss = TabularQLoss(TaskQTable(2, num_cells=4))
    with pytest.raises(ValueError, match="S=2 experiments .* batch_size \\[1\\]"):
        loss(td)


def _random_tables(batch, num_cells, generator, with_sensors=False):
    task = TaskQTable(batch, num_cells, with_sensors=with_sensors, sparse_grad=True)
    local = LocalRewardTable(batch)
    with torch.no_grad():
        task.table.copy_(torch.randn(task.table.shape, generator=generator) * 3)
        local.kappa.copy_(torch.randint(0, 9, local.kappa.shape, generator=generator))
        local.rho.copy_(-torch.rand(local.rho.shape, generator=generator) * (local.kappa > 0))
    return task, local


@pytest.mark.parametrize("algorithm", ["factor-q", "q-learning"])
@pytest.mark.parametrize("alpha", [0.2, 0.3, 0.77])
def test_tabular_step_equals_the_loss_its_gradient_and_one_sgd_step_bit_for_bit(algorithm, alpha):
    # Two copies of the same random tables: one moved by forward + backward + tabular_optimizer,
    # the other by tabular_step; finished experiments (mask False) keep their tables.
    generator = torch.Generator().manual_seed(int(alpha * 100))
    batch, num_cells = 512, 6
    q_learning = algorithm == "q-learning"
    td = random_batch(batch, num_cells, generator, local=not q_learning)
    td["collector", "mask"] = torch.rand(batch, generator=generator) < 0.8
    moved = []
    for _ in range(2):
        generator.manual_seed(7)
        task, local = _random_tables(batch, num_cells, generator, with_sensors=q_learning)
        if q_learning:
            loss = TabularQLoss(task, gamma=0.8, alpha=alpha)
        else:
            loss = FactorQLoss(task, local, gamma=0.8, alpha=alpha, eta=0.3, g_min=0.02)
        moved.append((task, local, loss))
    (task, local, loss), (task_d, local_d, loss_d) = moved
    initial = task.table.detach().clone()
    optimizer = tabular_optimizer(loss)
    loss(td.clone())["loss_task"].backward()
    optimizer.step()
    assert loss_d.supports_tabular_step() and loss_d.tabular_step(td.clone()) is True
    assert torch.equal(task.table.detach(), task_d.table.detach())
    assert torch.equal(local.rho, local_d.rho) and torch.equal(local.kappa, local_d.kappa)
    changed = (task_d.table.detach() != initial).flatten(1).any(1)
    assert changed.sum() > batch // 2 and not (changed & ~td["collector", "mask"]).any()


def test_tabular_step_leaves_a_frozen_table_and_in_eval_mode_the_local_tables_alone():
    generator = torch.Generator().manual_seed(3)
    task, local = _random_tables(64, 6, generator)
    td = random_batch(64, 6, generator)
    table, rho = task.table.detach().clone(), local.rho.clone()
    loss = FactorQLoss(task, local).eval()
    task.table.requires_grad_(False)
    assert loss.tabular_step(td) is True
    assert torch.equal(task.table, table) and torch.equal(local.rho, rho)


def test_tabular_step_refuses_what_it_cannot_do_and_skips_transitions_with_experiments():
    task, local = TaskQTable(2, 4), LocalRewardTable(2)
    with pytest.raises(ValueError, match="tabular_step needs a TaskQTable .* reduction='sum'"):
        FactorQLoss(task, local, reduction="mean").tabular_step(TensorDict(batch_size=[2]))
    network = TensorDictModule(torch.nn.Linear(4, 4), ["x"], ["action_value"])
    assert not TabularQLoss(network).supports_tabular_step()
    generator = torch.Generator().manual_seed(4)
    td = random_batch(2, 4, generator)
    td["experiment"] = torch.tensor([1, 1])
    table = task.table.detach().clone()
    assert FactorQLoss(task, local).tabular_step(td) is False
    assert torch.equal(task.table.detach(), table)


def test_tabular_step_names_a_state_past_the_table_and_an_action_out_of_range():
    generator = torch.Generator().manual_seed(5)
    task, local = _random_tables(2, 4, generator)
    loss = FactorQLoss(task, local)
    td = random_batch(2, 4, generator)
    td["cell"] = torch.tensor([0, 5])
    with pytest.raises(ValueError, match="num_cells=4 but received cell 5"):
        loss.tabular_step(td)
    td = random_batch(2, 4, generator)
    td["action"] = torch.tensor([4, 0])
    with pytest.raises(ValueError, match=r"action holds values outside \[0, 4\)"):
        loss.tabular_step(td)
