"""factorq_torch in ordinary torchrl use (issue 13): any batch of transitions, replay buffers and
torchrl's Collector, the exploration switch, specs that compose, clear errors where they enter."""

from __future__ import annotations

import copy
import runpy
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.envs import (
    Compose,
    InitTracker,
    RewardSum,
    SerialEnv,
    StepCounter,
    TransformedEnv,
)
from torchrl.envs.utils import ExplorationType, check_env_specs, set_exploration_type

from envs import ExperimentIndex, FactoredGridEnv, SplitLocalReward
from factorq_torch.collectors import OnlineCollector
from factorq_torch.objectives import FactorQLoss, TabularQLoss, tabular_optimizer
from factorq_torch.policy import EpsilonGreedyPolicy, FactorQPolicy
from factorq_torch.tables import LocalRewardTable, TaskQTable

ROOT = Path(__file__).resolve().parent.parent


def factorq(S: int, cells: int = 16, epsilon: float = 0.2, seed: int = 0):
    task, local = TaskQTable(S, num_cells=cells), LocalRewardTable(S)
    actor = TensorDictSequential(task, local, FactorQPolicy(S, seed=seed, epsilon=epsilon))
    return task, local, actor, FactorQLoss(task, local)


def split_env(S=4, seed=0, **world):
    world = {"size": 4, "num_obstacles": 3, "obstacle_period": 1, **world}
    base = FactoredGridEnv(**world, batch_size=(S,), seed=seed)
    return TransformedEnv(base, Compose(SplitLocalReward(), ExperimentIndex()))


def learn(loss, td):
    optimizer = tabular_optimizer(loss)
    loss(td)["loss_task"].backward()
    optimizer.step()
    optimizer.zero_grad()


def tables_of(task, local):
    return task.table.detach().clone(), local.rho.clone(), local.kappa.clone()


def assert_same_tables(first, second):
    for a, b in zip(first, second, strict=True):
        assert torch.equal(a, b)


# -- 1. any batch of transitions -----------------------------------------------------------------


def test_a_shuffled_minibatch_with_experiment_keys_equals_the_online_step_bit_for_bit():
    S = 4
    env = split_env(S)
    task, local, actor, loss = factorq(S)
    with torch.no_grad():
        data = env.rollout(40, actor, break_when_any_done=False)  # [S, T]
    learn(loss, data[:, 0])  # warm the tables up so the step below moves non-zero values
    step = data[:, 1]  # one online step of the S experiments, batch [S]
    assert torch.equal(step["experiment"], torch.arange(S))
    shuffled = step[torch.tensor([2, 0, 3, 1])]  # a minibatch: order lost, keys kept
    twin_task, twin_local = copy.deepcopy(task), copy.deepcopy(local)
    learn(loss, step)
    learn(FactorQLoss(twin_task, twin_local), shuffled)
    assert_same_tables(tables_of(task, local), tables_of(twin_task, twin_local))


def test_an_s_by_t_rollout_needs_no_experiment_key_and_equals_its_flattened_form():
    S = 3
    env = TransformedEnv(
        FactoredGridEnv(size=4, num_obstacles=3, batch_size=(S,)), SplitLocalReward()
    )
    task, local, actor, loss = factorq(S)
    with torch.no_grad():
        data = env.rollout(20, actor, break_when_any_done=False)  # [S, T], no "experiment"
    flat = data.reshape(-1)
    flat["experiment"] = torch.arange(S).repeat_interleave(20)
    twin_task, twin_local = copy.deepcopy(task), copy.deepcopy(local)
    learn(loss, data)
    learn(FactorQLoss(twin_task, twin_local), flat)
    assert_same_tables(tables_of(task, local), tables_of(twin_task, twin_local))
    assert int(local.kappa.sum()) == S * 20


def test_duplicates_of_one_entry_move_it_by_the_mean_td_error_and_merge_the_running_mean():
    task, local = TaskQTable(1, num_cells=4), LocalRewardTable(1)
    with torch.no_grad():
        task.table[0, 0, 3] = 1.0  # Q(s, east) = 1
    # the same (s, a) twice, terminal, task rewards -1 and -3: TD errors 1 - (-1) = 2, 4
    td = TensorDict(
        cell=torch.tensor([0, 0]),
        sensors=torch.tensor([[True, False, False, True]] * 2),  # the east sensor is on
        action=torch.tensor([3, 3]),
        experiment=torch.tensor([0, 0]),
        next=TensorDict(
            cell=torch.tensor([1, 1]),
            sensors=torch.zeros(2, 4, dtype=torch.bool),
            reward=torch.tensor([[-1.0], [-3.0]]),
            local_reward=torch.tensor([[0.0, 0, 0, -1.0], [0.0, 0, 0, 0.0]]),
            terminated=torch.ones(2, 1, dtype=torch.bool),
            batch_size=[2],
        ),
        batch_size=[2],
    )
    learn(FactorQLoss(task, local), td)
    # Q <- Q - alpha * mean(TD error) = 1 - 0.2 * 3 = 0.4 (a sum would give 1 - 0.2 * 6)
    assert task.table[0, 0, 3].item() == pytest.approx(0.4)
    # eq. 5 with both rewards: kappa = 2, rho = mean(-1, 0) = -0.5
    assert local.kappa[0, 3, 1].item() == 2 and local.rho[0, 3, 1].item() == -0.5


def test_one_experiment_takes_any_batch_shape_and_an_unbatched_env():
    env = TransformedEnv(FactoredGridEnv(size=3, num_obstacles=1), SplitLocalReward())  # []
    task, local, actor, loss = factorq(1, cells=9)
    with torch.no_grad():
        data = env.rollout(30, actor, break_when_any_done=False)  # [T]
    learn(loss, data)
    learn(loss, data.reshape(5, 6))
    assert int(local.kappa.sum()) == 60


def test_tabular_q_learning_trains_from_replay_minibatches():
    S = 2
    env = FactoredGridEnv(size=4, num_obstacles=2, batch_size=(S,))
    env = TransformedEnv(env, ExperimentIndex())
    table = TaskQTable(S, num_cells=16, with_proximity=True)
    actor = TensorDictSequential(table, EpsilonGreedyPolicy(S, epsilon=0.3))
    buffer = ReplayBuffer(storage=LazyTensorStorage(1000), batch_size=32)
    with torch.no_grad():
        buffer.extend(env.rollout(50, actor, break_when_any_done=False).reshape(-1))
    loss = TabularQLoss(table)
    out = loss(buffer.sample())
    assert out["td_error"].shape == (32,)
    learn(loss, buffer.sample())
    assert (table.table != 0).any()


@pytest.mark.slow
def test_off_policy_example_learns_from_a_replay_buffer_filled_by_torchrl_collector():
    train = runpy.run_path(str(ROOT / "examples" / "offpolicy_replay.py"))["train"]
    result = train()
    steps, collisions = result["steps"], result["collisions"]
    # the first batch is exploration on empty tables: no episode ends, a third of steps collide
    assert collisions[0] > 0.15
    assert sum(collisions[-5:]) / 5 < collisions[0] / 4
    late = [s for s in steps[-5:] if s == s]  # NaN-free
    early = [s for s in steps[:5] if s == s]
    assert late and sum(late) / len(late) < 40
    assert not early or sum(late) / len(late) < sum(early) / len(early)
    assert result["greedy_steps"] == [8.0] * 4  # the shortest path of a 5x5 grid


# -- 2. exploration types ------------------------------------------------------------------------


@pytest.mark.parametrize("kind", [ExplorationType.DETERMINISTIC, ExplorationType.MODE])
def test_greedy_exploration_types_make_the_policy_greedy_with_random_ties(kind):
    policy = EpsilonGreedyPolicy(1000, epsilon=0.5)
    values = torch.tensor([[1.0, 3.0, 3.0, 0.0]]).expand(1000, 4)
    with set_exploration_type(kind):
        td = policy(TensorDict(action_value=values, batch_size=[1000]))
    assert not td["exploratory"].any()
    assert set(td["action"].tolist()) == {1, 2}  # both maxima, drawn at random


def test_random_exploration_type_and_the_default_explore_with_epsilon():
    values = torch.zeros(2000, 4)
    for context in (set_exploration_type(ExplorationType.RANDOM), torch.no_grad()):
        policy = FactorQPolicy(2000, epsilon=0.5)
        with context:
            td = policy(TensorDict(action_value=values, local_value=values, batch_size=[2000]))
        assert 0.45 < td["exploratory"].float().mean() < 0.55


# -- 3. specs that compose -----------------------------------------------------------------------


def composed(seed: int, S: int | None = 3):
    base = FactoredGridEnv(
        size=4, num_obstacles=3, obstacle_period=1, max_steps=40, batch_size=S, seed=seed
    )
    transforms = Compose(
        SplitLocalReward(),
        StepCounter(),
        InitTracker(),
        RewardSum(in_keys=["reward", "local_reward"]),
    )
    return TransformedEnv(base, transforms)


@pytest.mark.parametrize("seed", range(5))
def test_check_env_specs_passes_with_step_counter_reward_sums_and_init_tracker(seed):
    env = composed(seed)
    env.append_transform(ExperimentIndex())
    check_env_specs(env, seed=seed)
    data = env.rollout(100, break_when_any_done=False)
    assert data["next", "episode_local_reward"].min() < -1  # sums below the step's bound


def test_serial_env_of_single_worlds_passes_check_env_specs():
    env = SerialEnv(3, [lambda seed=seed: composed(seed, None) for seed in range(3)])
    check_env_specs(env, seed=0)
    env.close()


def test_split_local_reward_as_a_replay_buffer_transform_splits_sampled_transitions():
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2,))
    data = env.rollout(30, break_when_any_done=False).reshape(-1)
    buffer = ReplayBuffer(storage=LazyTensorStorage(100), transform=SplitLocalReward())
    buffer.extend(data)
    sample = buffer.sample(16)
    task = sample["next", "reward"] + sample["next", "collision"].sum(-1, keepdim=True)
    assert torch.equal(sample["next", "local_reward"], sample["next", "collision"])
    assert set(task.unique().tolist()) <= {-2.0, -1.0, 0.0, 1.0} and task.max() <= 0
    with pytest.raises(ValueError, match="already split"):
        SplitLocalReward()(sample)


# -- 6. clear errors -----------------------------------------------------------------------------


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_where_torch_has_none_is_refused_where_it_enters():
    for build in (
        lambda: FactoredGridEnv(device="cuda"),
        lambda: TaskQTable(1, num_cells=4, device="cuda"),
        lambda: LocalRewardTable(1, device="cuda:0"),
        lambda: FactorQPolicy(1, device="cuda"),
    ):
        with pytest.raises(ValueError, match="device='cuda(:0)?' but this torch .* no CUDA"):
            build()


def test_stepping_before_any_reset_is_refused():
    env = FactoredGridEnv(size=3, num_obstacles=1)
    with pytest.raises(RuntimeError, match="before any reset"):
        env.step(TensorDict(action=torch.tensor(0), batch_size=[]))


def test_a_table_smaller_than_the_env_is_refused_naming_num_cells():
    env = TransformedEnv(
        FactoredGridEnv(size=5, num_obstacles=3, batch_size=(2,)), SplitLocalReward()
    )
    task, local, actor, loss = factorq(2, cells=16)
    with pytest.raises(ValueError, match="num_cells=16 but the env has 25 cells"):
        OnlineCollector(env, actor, loss, runs=1, episodes=1)
    td = env.reset()
    td["cell"] = torch.tensor([24, 3])
    with pytest.raises(ValueError, match="num_cells=16 but received cell 24"):
        task(td)


def test_a_two_by_four_env_batch_given_to_eight_tables_names_the_batch_and_the_remedy():
    env = FactoredGridEnv(size=3, num_obstacles=1, batch_size=(2, 4))
    task, local, actor, loss = factorq(8, cells=9)
    with pytest.raises(ValueError, match=r"S=8 experiments .* batch_size \[2, 4\] .*'experiment'"):
        actor(env.reset())
    indexed = TransformedEnv(env, Compose(SplitLocalReward(), ExperimentIndex()))
    with torch.no_grad():
        data = indexed.rollout(5, actor, break_when_any_done=False)  # [2, 4, T]
    learn(loss, data)
    assert int(local.kappa.sum()) == 8 * 5
