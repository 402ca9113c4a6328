"""TaskQTable and LocalRewardTable: one table per experiment, read and reset as the SPEC says."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from factorq_torch.tables import LocalRewardTable, TaskQTable


def test_task_table_writes_each_experiments_row_for_its_cell():
    table = TaskQTable(2, num_cells=4)
    with torch.no_grad():
        table.table[0, 1] = torch.tensor([1.0, 2.0, 3.0, 4.0])
        table.table[1, 1] = torch.tensor([5.0, 6.0, 7.0, 8.0])  # same cell, other experiment
    td = TensorDict(cell=torch.tensor([1, 1]), batch_size=[2])
    expected = torch.tensor([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]])
    assert torch.equal(table(td)["action_value"], expected)


def test_qlearning_table_indexes_cell_times_16_plus_the_proximity_pattern():
    table = TaskQTable(1, num_cells=4, with_sensors=True)
    assert table.table.shape == (1, 64, 4)
    with torch.no_grad():
        table.table[0, 3 * 16 + 9] = torch.tensor([1.0, 0.0, 0.0, 0.0])  # pattern N + E = 1 + 8
    proximity = torch.tensor([[True, False, False, True]])
    td = TensorDict(cell=torch.tensor([3]), sensors=proximity, batch_size=[1])
    assert table(td)["action_value"].tolist() == [[1.0, 0.0, 0.0, 0.0]]
    td["sensors"] = torch.tensor([[True, False, False, False]])  # pattern 1: another state
    assert table(td)["action_value"].tolist() == [[0.0, 0.0, 0.0, 0.0]]


def test_task_table_gradient_reaches_only_the_visited_entries():
    table = TaskQTable(2, num_cells=3)
    td = TensorDict(cell=torch.tensor([2, 0]), batch_size=[2])
    table(td)["action_value"][:, 1].sum().backward()
    expected = torch.zeros(2, 3, 4)
    expected[0, 2, 1] = expected[1, 0, 1] = 1.0
    assert torch.equal(table.table.grad, expected)


def test_sparse_grad_table_holds_the_same_gradient_and_sgd_step_bit_for_bit():
    # sparse_grad=True: no dense [S, states, A] gradient; the same entries, the same update.
    generator = torch.Generator().manual_seed(0)
    count, cells = 64, 25
    start = torch.randn(count, cells * 16, 4, generator=generator)
    tables = []
    for sparse in (False, True):
        table = TaskQTable(count, num_cells=cells, with_sensors=True, sparse_grad=sparse)
        with torch.no_grad():
            table.table.copy_(start)
        tables.append(table)
    optimizers = [torch.optim.SGD(table.parameters(), lr=1.0) for table in tables]
    for _ in range(5):
        cell = torch.randint(0, cells, (count,), generator=generator)
        sensors = torch.randint(0, 2, (count, 4), generator=generator).bool()
        action = torch.randint(0, 4, (count,), generator=generator)
        target = torch.randn(count, generator=generator)
        gradients = []
        for table, optimizer in zip(tables, optimizers, strict=True):
            td = TensorDict(cell=cell, sensors=sensors, batch_size=[count])
            q_sa = table(td)["action_value"].gather(1, action.unsqueeze(1)).squeeze(1)
            (0.2 * (0.5 * (q_sa - target).pow(2))).sum().backward()
            gradients.append(table.table.grad)
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        assert gradients[1].is_sparse and not gradients[0].is_sparse
        assert torch.equal(gradients[1].to_dense(), gradients[0])
    assert torch.equal(tables[0].table, tables[1].table)


def test_reset_task_zeroes_only_the_masked_experiments():
    table = TaskQTable(3, num_cells=2)
    with torch.no_grad():
        table.table.fill_(1.5)
    table.reset_task(torch.tensor([False, True, False]))
    assert table.table[1].abs().sum() == 0
    assert (table.table[[0, 2]] == 1.5).all()
    table.reset_task()
    assert table.table.abs().sum() == 0


def test_local_table_reads_rho_of_each_sensor_at_its_reading():
    local = LocalRewardTable(1)
    with torch.no_grad():
        local.rho[0] = torch.tensor([[0.0, -1.0], [-0.1, -0.2], [-0.3, -0.4], [-0.5, -0.6]])
    proximity = torch.tensor([[True, False, True, False]])
    td = TensorDict(sensors=proximity, batch_size=[1])
    # sensor 0 reads 1 -> rho_0[1] = -1; sensor 1 reads 0 -> -0.1; -0.4; -0.5
    assert torch.allclose(local(td)["local_value"], torch.tensor([[-1.0, -0.1, -0.4, -0.5]]))


def test_local_update_is_a_running_mean_of_the_fired_actuator_at_its_reading_before_acting():
    local = LocalRewardTable(2)
    proximity = torch.tensor([[True, False, False, False], [True, False, False, False]])
    action = torch.tensor([0, 2])  # 0 fires north with the sensor on; 1 fires south, sensor off
    local.update_running_mean(proximity, action, torch.tensor([[-1.0, 0, 0, 0], [0.0] * 4]))
    local.update_running_mean(proximity, action, torch.tensor([[0.0] * 4, [0.0] * 4]))
    # experiment 0: rho_0[1] = mean(-1, 0) = -0.5 after 2 visits; experiment 1: rho_2[0] = 0
    assert local.kappa[0, 0, 1] == 2 and local.rho[0, 0, 1] == -0.5
    assert local.kappa[1, 2, 0] == 2 and local.rho[1, 2, 0] == 0.0
    assert local.kappa.sum() == 4  # nothing else was visited


def test_the_online_update_through_numpy_is_the_batched_update_bit_for_bit():
    """One transition per experiment on the CPU is read and written through numpy
    (``LocalRewardTable._update_online``); a mask of all True takes the batched tensor ops."""
    generator = torch.Generator().manual_seed(26)
    dependency = torch.tensor(  # pairs, a single parent and none: patterns of 0-2 bits
        [
            [True, False, True, False],
            [False, True, False, False],
            [False] * 4,
            [True] * 2 + [False] * 2,
        ]
    )
    for experiments in (1, 3):
        fast, batched = (LocalRewardTable(experiments, dependency=dependency) for _ in range(2))
        versions = fast.rho._version, fast.kappa._version
        for step in range(300):
            readings = torch.rand(experiments, 4, generator=generator) < 0.5
            action = torch.randint(0, 4, (experiments,), generator=generator)
            reward = -torch.rand(experiments, 4, generator=generator) * (step % 3)
            if step % 2:
                fast.update_running_mean(readings, action, reward)
            else:  # (the path it takes)
                assert fast._update_online(readings, action, reward)
            everything = torch.ones(experiments, dtype=torch.bool)
            batched.update_running_mean(readings, action, reward, mask=everything)
        assert torch.equal(fast.rho.view(torch.int32), batched.rho.view(torch.int32))
        assert torch.equal(fast.kappa, batched.kappa) and fast.kappa.sum() == 300 * experiments
        assert (fast.rho._version, fast.kappa._version) == (versions[0] + 300, versions[1] + 300)
    with pytest.raises(ValueError, match="action"):  # its errors are the batched update's
        fast.update_running_mean(readings, torch.tensor([4, 0, 0]), reward)
    with pytest.raises(ValueError, match="local_reward"):
        fast.update_running_mean(readings, action, torch.full((3, 4), float("nan")))
    assert torch.equal(fast.kappa, batched.kappa)  # nothing written


def test_the_online_read_through_numpy_is_project_local_bit_for_bit():
    """``LocalRewardTable.local_values`` of a few CPU experiments reads ``rho`` through numpy at
    indices remembered by reading (``_local_values_read``): the entries ``project_local``
    gathers, through updates, a dependency changed in place and another ``rho`` dtype."""
    from factorq_torch.functional import project_local

    generator = torch.Generator().manual_seed(42)
    dependency = torch.tensor(  # pairs, a single parent and none: patterns of 0-2 bits
        [[True, False, True, False], [False, True, False, False], [False] * 4, [True] * 4]
    )
    for experiments in (1, 3):
        local = LocalRewardTable(experiments, dependency=dependency)
        for step in range(200):
            readings = torch.rand(experiments, 4, generator=generator) < 0.5
            if step == 100:  # a new dependency in place: the remembered indices are dropped
                local.dependency[3, 1:] = False
            if step == 150:
                local.rho = local.rho.double()
            fast = local.local_values(readings)
            expected = project_local(local.rho, readings, local.dependency)
            assert fast.dtype == expected.dtype and fast.shape == (experiments, 4)
            assert torch.equal(fast.view(torch.int8), expected.view(torch.int8))
            action = torch.randint(0, 4, (experiments,), generator=generator)
            reward = -torch.rand(experiments, 4, generator=generator, dtype=torch.float64)
            local.update_running_mean(readings, action, reward.to(local.rho.dtype))
        assert local.__dict__["_read_index"][1]  # (the read path ran)
        local.rho.requires_grad_(True)  # anything else: project_local itself
        assert local.local_values(readings).requires_grad


def test_local_update_leaves_masked_experiments_alone():
    local = LocalRewardTable(2)
    proximity = torch.ones(2, 4, dtype=torch.bool)
    collision = torch.tensor([[-1.0, 0, 0, 0]] * 2)
    local.update_running_mean(
        proximity, torch.tensor([0, 0]), collision, mask=torch.tensor([True, False])
    )
    assert local.rho[0, 0, 1] == -1.0 and local.kappa[0].sum() == 1
    assert local.rho[1].abs().sum() == 0 and local.kappa[1].sum() == 0


def test_local_tables_are_reset_only_explicitly_and_only_where_masked():
    local = LocalRewardTable(2)
    with torch.no_grad():
        local.rho.fill_(-0.25)
        local.kappa.fill_(3)
    local.reset(torch.tensor([True, False]))
    assert local.rho[0].abs().sum() == 0 and local.kappa[0].sum() == 0
    assert (local.rho[1] == -0.25).all() and (local.kappa[1] == 3).all()


def test_tables_round_trip_through_state_dict():
    local, other = LocalRewardTable(1), LocalRewardTable(1)
    local.update_running_mean(
        torch.ones(1, 4, dtype=torch.bool), torch.tensor([3]), torch.tensor([[0, 0, 0, -1.0]])
    )
    other.load_state_dict(local.state_dict())
    assert torch.equal(other.rho, local.rho) and torch.equal(other.kappa, local.kappa)


# -- bad input ---------------------------------------------------------------------------------


def test_a_tensordict_with_another_batch_size_is_refused_with_both_sizes_named():
    table = TaskQTable(3, num_cells=4)
    with pytest.raises(ValueError, match=r"S=3 experiments .* batch_size \[2\]"):
        table(TensorDict(cell=torch.tensor([0, 1]), batch_size=[2]))
    with pytest.raises(ValueError, match=r"S=3 experiments"):
        LocalRewardTable(3)(TensorDict(sensors=torch.ones(2, 4, dtype=torch.bool), batch_size=[2]))


def test_misshapen_or_mistyped_observations_are_refused():
    table = TaskQTable(1, num_cells=4, with_sensors=True)
    bad_proximity = TensorDict(
        cell=torch.tensor([0]), sensors=torch.ones(1, 3, dtype=torch.bool), batch_size=[1]
    )
    with pytest.raises(ValueError, match="'sensors' has shape \\[1, 3\\]"):
        table(bad_proximity)
    with pytest.raises(ValueError, match="'cell' has shape \\[1\\] and dtype torch.float32"):
        table(TensorDict(cell=torch.tensor([0.0]), batch_size=[1]))
    with pytest.raises(KeyError, match="needs 'cell'"):
        table(TensorDict(batch_size=[1]))


def test_bad_sizes_and_masks_are_refused():
    with pytest.raises(ValueError, match="num_experiments=0"):
        TaskQTable(0, num_cells=4)
    with pytest.raises(TypeError, match="num_cells must be an int"):
        TaskQTable(1, num_cells=4.0)
    with pytest.raises(ValueError, match="mask has shape \\[3\\], expected \\[2\\]"):
        TaskQTable(2, num_cells=4).reset_task(torch.ones(3, dtype=torch.bool))
    with pytest.raises(TypeError, match="bool tensor"):
        LocalRewardTable(2).reset(torch.ones(2))
    with pytest.raises(ValueError, match="action has shape \\[1\\], expected \\[2\\]"):
        LocalRewardTable(2).update_running_mean(
            torch.ones(2, 4, dtype=torch.bool), torch.tensor([0]), torch.zeros(2, 4)
        )


@pytest.mark.parametrize("sparse_grad", [False, True])
@pytest.mark.parametrize("grad", [False, True])
@pytest.mark.parametrize("cell", [4, -1, -4])
def test_a_cell_outside_the_table_is_refused_on_every_read_path(sparse_grad, grad, cell):
    # the online read (one gather), the sparse-gradient and the dense-gradient reads: a negative
    # cell must not wrap around to the last rows
    table = TaskQTable(3, num_cells=4, sparse_grad=sparse_grad)
    td = TensorDict(cell=torch.tensor([0, cell, 1]), batch_size=[3])
    with torch.set_grad_enabled(grad), pytest.raises(ValueError, match="num_cells=4"):
        table(td)


def test_the_online_read_gives_each_experiments_own_row():
    table = TaskQTable(3, num_cells=5)
    with torch.no_grad():
        table.table.copy_(torch.arange(60, dtype=torch.float32).view(3, 5, 4))
        values = table(TensorDict(cell=torch.tensor([4, 0, 2]), batch_size=[3]))["action_value"]
    assert values.tolist() == [
        [16.0, 17.0, 18.0, 19.0],
        [20.0, 21.0, 22.0, 23.0],
        [48.0, 49.0, 50.0, 51.0],
    ]
