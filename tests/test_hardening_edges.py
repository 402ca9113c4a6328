"""Hardening, round three (issue 41, item 4): values at the library's edge (``factorq_torch``
and the compiled kernel) that overflow, wrap or are not finite are refused where they enter,
and nothing is written."""

from __future__ import annotations

import json

import pytest
import torch
from tensordict import TensorDict

from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys
from factorq_torch.objectives import FactorQLoss, TabularQLoss
from factorq_torch.tables import LocalRewardTable, TaskQTable

S, CELLS = 3, 4
F32_MAX = float(torch.finfo(torch.float32).max)


def step(reward: torch.Tensor | None = None, local: torch.Tensor | None = None) -> TensorDict:
    """One online transition of S experiments (actions 0, 1, 2)."""
    return TensorDict(
        {
            "cell": torch.tensor([0, 1, 2]),
            "sensors": torch.zeros(S, 4, dtype=torch.bool),
            "action": torch.tensor([0, 1, 2]),
            "next": TensorDict(
                {
                    "cell": torch.tensor([1, 2, 3]),
                    "sensors": torch.zeros(S, 4, dtype=torch.bool),
                    "reward": torch.full((S, 1), -1.0) if reward is None else reward,
                    "local_reward": torch.zeros(S, 4) if local is None else local,
                    "terminated": torch.zeros(S, 1, dtype=torch.bool),
                },
                [S],
            ),
        },
        batch_size=[S],
    )


@pytest.mark.parametrize("online", [True, False])
def test_a_running_mean_that_would_overflow_is_refused_and_the_table_kept(online):
    table = LocalRewardTable(S)
    readings = torch.zeros(S, 4, dtype=torch.bool)
    action = torch.zeros(S, dtype=torch.int64)
    first = torch.zeros(S, 4)
    first[:, 0] = 1e38
    table.update_running_mean(readings, action, first)
    assert torch.equal(table.rho[:, 0, 0], torch.full((S,), 1e38))
    rho, kappa = table.rho.clone(), table.kappa.clone()
    second = torch.zeros(S, 4)
    second[:, 0] = -3.4e38  # r - rho = -4.4e38: past float32's range
    mask = None if online else torch.ones(S, dtype=torch.bool)  # (a mask: the tensor path)
    with pytest.raises(ValueError, match=r"running mean \(eq. 5\) holds NaN or infinite .*1.7e38"):
        table.update_running_mean(readings, action, second, mask)
    assert torch.equal(table.rho, rho) and torch.equal(table.kappa, kappa)


def test_eq5_is_unchanged_for_rewards_that_do_not_overflow():
    """Hand-computed: rewards 1, -2, 4 on one entry average to 1 (eq. 5, one at a time)."""
    table = LocalRewardTable(1)
    readings = torch.zeros(1, 4, dtype=torch.bool)
    for reward in (1.0, -2.0, 4.0):
        table.update_running_mean(readings, torch.tensor([3]), torch.tensor([[0, 0, 0, reward]]))
    assert table.rho[0, 3, 0].item() == 1.0 and table.kappa[0, 3, 0].item() == 3


@pytest.mark.parametrize("how", ["forward", "tabular_step"])
@pytest.mark.parametrize("make", ["factor-q", "q-learning"])
def test_a_step_whose_target_overflows_is_refused_and_writes_nothing(how, make):
    task = TaskQTable(S, CELLS, sparse_grad=True)
    with torch.no_grad():
        task.table.fill_(3e38)  # finite values ...
    loss = FactorQLoss(task, LocalRewardTable(S)) if make == "factor-q" else TabularQLoss(task)
    before = task.table.detach().clone()
    reward = torch.full((S, 1), 3e38)  # ... and a finite reward: r + gamma Q(s') overflows
    with pytest.raises(ValueError, match="NaN or infinite values"):
        loss(step(reward)) if how == "forward" else loss.tabular_step(step(reward))
    assert torch.equal(task.table.detach(), before)


@pytest.mark.parametrize("how", ["forward", "tabular_step"])
def test_a_float64_reward_is_one_clear_error(how):
    loss = FactorQLoss(TaskQTable(S, CELLS, sparse_grad=True), LocalRewardTable(S))
    reward = torch.full((S, 1), -1.0, dtype=torch.float64)
    with pytest.raises(TypeError, match=r"'reward'\) is torch.float64 but the values are "):
        loss(step(reward)) if how == "forward" else loss.tabular_step(step(reward))


@pytest.mark.parametrize(
    ("module", "name"),
    [(lambda: TaskQTable(S, CELLS), "table"), (lambda: LocalRewardTable(S), "rho")],
)
def test_load_state_dict_refuses_nan_tables_and_loads_nothing(module, name):
    target = module()
    state = {key: value.clone() for key, value in target.state_dict().items()}
    state[name][1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=rf"load_state_dict: '{name}' holds NaN .*experiment 1"):
        target.load_state_dict(state)
    assert not bool(getattr(target, name).isnan().any())


def test_load_state_dict_refuses_negative_visit_counts():
    table = LocalRewardTable(S)
    state = table.state_dict()
    state["kappa"][0, 0, 0] = -1
    with pytest.raises(ValueError, match="'kappa' holds negative counts"):
        table.load_state_dict(state)


def _batch():
    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_trainers.compiled import fast

    if not fast.is_available():
        pytest.skip(f"no compiled kernel: {fast.unavailable_reason()}")
    return fast.ExperimentBatch(
        "factor-q",
        torch.tensor([0, 1]),
        WorldConfig(size=4, num_obstacles=1, max_steps=20),
        AgentConfig(),
        runs=1,
        episodes=2,
        world_keys=derive_keys(0, STREAM_WORLD, 2),
        policy_keys=derive_keys(0, STREAM_POLICY, 2),
    )


@pytest.mark.parametrize("steps", [2**63, 2**64 + 5, -1])
def test_advance_refuses_step_counts_outside_int64(steps):
    batch = _batch()
    with pytest.raises(
        ValueError, match=r"max_steps=.* is out of range: must be in \[0, 9223372036854775807\]"
    ):
        batch.advance(steps)
    assert batch.total_steps == 0


def test_advance_within_range_still_runs():
    batch = _batch()
    batch.advance(5)
    assert batch.total_steps == 2 * 5


def test_load_state_dict_of_a_batch_refuses_nan_tables():
    batch = _batch()
    state = batch.state_dict()
    float_names = [name for name, value in state.items() if value.is_floating_point()]
    assert float_names
    state[float_names[0]].view(-1)[0] = float("nan")
    with pytest.raises(ValueError, match=rf"state\['{float_names[0]}'\] holds NaN"):
        batch.load_state_dict(state)


@pytest.mark.parametrize(
    ("argument", "value"), [("key", 2**64), ("key", 2**63), ("scatter_index", -1), ("agent", 16)]
)
def test_kernel_scatter_refuses_values_ctypes_would_wrap(argument, value):
    import kernel_probes  # tests/kernel_probes.py

    from factorq_trainers.compiled import fast

    if not fast.is_available():
        pytest.skip(f"no compiled kernel: {fast.unavailable_reason()}")
    arguments = {"size": 4, "num_obstacles": 2, "key": 7, "scatter_index": 0, "agent": 5}
    arguments[argument] = value
    with pytest.raises(ValueError, match=rf"{argument}={value} is out of range"):
        kernel_probes.kernel_scatter(**arguments)
    wrapped = dict(arguments, **{argument: {"key": 0, "scatter_index": 0, "agent": 5}[argument]})
    assert kernel_probes.kernel_scatter(**wrapped).sum() == 2


def test_report_refuses_a_results_file_with_impossible_fractions(tmp_path):
    from factorq_trainers import reports

    (tmp_path / "dependencies.json").write_text(
        json.dumps(
            {
                "schema_version": 1,
                "command": "dependencies",
                "config": {},
                "settings": {"x": {"structure": {"fraction_right_within_target": 1e308}}},
            }
        )
    )
    with pytest.raises(ValueError, match=r"fraction_right_within_target holds 1e\+308, not a frac"):
        reports.regenerate(tmp_path)
    assert not (tmp_path / "dependencies.md").exists()
