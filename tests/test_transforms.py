"""SplitLocalReward and the state-index helpers (envs/transforms.py)."""

import pytest
import torch
from torchrl.data import Unbounded
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs, step_mdp

from factorq_envs import FactoredGridEnv, SplitLocalReward
from factorq_torch.functional import qlearning_state
from factorq_torch.functional import sensor_pattern as proximity_pattern

NORTH, WEST, SOUTH, EAST = range(4)


def split_env(**kwargs) -> TransformedEnv:
    return TransformedEnv(FactoredGridEnv(**kwargs), SplitLocalReward())


def test_split_gives_task_reward_and_collision_vector_for_wall_move_and_goal():
    # 2x2, no obstacles, three worlds: a wall bump, a free move, and (after one move) the goal.
    env = split_env(size=2, num_obstacles=0, batch_size=(3,))
    td = env.reset()
    td["action"] = torch.tensor([WEST, EAST, EAST])
    td = env.step(td)
    nxt = td["next"]
    # Conventional rewards were -2 (bump), -1, -1: task rewards -1, -1, -1.
    assert nxt["reward"].flatten().tolist() == [-1.0, -1.0, -1.0]
    assert nxt["local_reward"].tolist() == [[0.0, -1.0, 0.0, 0.0], [0.0] * 4, [0.0] * 4]
    td = step_mdp(td)
    td["action"] = torch.tensor([NORTH, SOUTH, SOUTH])  # world 0 bumps north, 1 and 2 reach goal
    nxt = env.step(td)["next"]
    assert nxt["reward"].flatten().tolist() == [-1.0, 0.0, 0.0]  # goal: -1 + 1
    assert nxt["local_reward"].tolist() == [[-1.0, 0.0, 0.0, 0.0], [0.0] * 4, [0.0] * 4]


def test_task_plus_local_reward_equals_the_conventional_reward_on_a_long_rollout():
    settings = dict(size=5, num_obstacles=6, obstacle_period=[0, 10, 1, 1], batch_size=(4,))
    plain = FactoredGridEnv(**settings, seed=3)
    split = split_env(**settings, seed=3)
    torch.manual_seed(0)
    reference = plain.rollout(200, break_when_any_done=False)
    torch.manual_seed(0)
    data = split.rollout(200, break_when_any_done=False)
    assert torch.equal(data["action"], reference["action"])
    task, local = data["next", "reward"], data["next", "local_reward"]  # [4, 200, 1], [4, 200, 4]
    assert torch.equal(task + local.sum(-1, keepdim=True), reference["next", "reward"])
    assert torch.equal(local, reference["next", "collision"])
    assert set(task.unique().tolist()) <= {-1.0, 0.0}
    assert (local == -1).any() and (task == 0).any()  # the rollout saw collisions and goals


def test_local_reward_is_a_copy_not_the_collision_entry_itself():
    env = split_env(size=3, num_obstacles=0)
    td = env.reset()
    td["action"] = torch.tensor(NORTH)
    nxt = env.step(td)["next"]
    nxt["local_reward"].zero_()
    assert nxt["collision"].tolist() == [-1.0, 0.0, 0.0, 0.0]


@pytest.mark.parametrize("batch_size", [(), (1,), (64,)])
def test_transformed_env_passes_check_env_specs(batch_size):
    check_env_specs(split_env(batch_size=batch_size, obstacle_period=1))


def test_specs_declare_local_reward_next_to_an_unchanged_reward():
    base = FactoredGridEnv(batch_size=(7,))
    env = TransformedEnv(base, SplitLocalReward())
    reward_spec = env.full_reward_spec
    assert set(reward_spec.keys()) == {"reward", "local_reward"}
    assert reward_spec["local_reward"].shape == (7, 4)
    assert reward_spec["local_reward"].dtype == torch.float32
    # unbounded: an episode's sum (torchrl's RewardSum) goes below the step's -1 (issue 13)
    assert isinstance(reward_spec["local_reward"], Unbounded)
    assert reward_spec["reward"] == base.full_reward_spec["reward"]
    assert set(env.reward_keys) == {"reward", "local_reward"}
    assert "reward" not in env.reset().keys()  # a reset carries no reward to split


def test_transform_refuses_an_env_without_the_collision_entry():
    env = TransformedEnv(FactoredGridEnv(), SplitLocalReward(collision_key="crash"))
    with pytest.raises(KeyError, match="crash"):
        _ = env.output_spec


def test_forward_splits_a_tensordict_offline():
    from tensordict import TensorDict

    data = TensorDict(
        reward=torch.tensor([[-2.0], [0.0]]),
        collision=torch.tensor([[0.0, 0.0, -1.0, 0.0], [0.0] * 4]),
        batch_size=[2],
    )
    out = SplitLocalReward()(data)
    assert out["reward"].flatten().tolist() == [-1.0, 0.0]
    assert out["local_reward"][0].tolist() == [0.0, 0.0, -1.0, 0.0]


def test_proximity_pattern_sums_bit_i_shifted_by_i():
    sensors = torch.tensor(
        [
            [False, False, False, False],  # 0
            [True, False, False, False],  # 1
            [False, True, False, True],  # 2 + 8 = 10
            [True, True, True, True],  # 15
        ]
    )
    assert proximity_pattern(sensors).tolist() == [0, 1, 10, 15]
    assert proximity_pattern(sensors).dtype == torch.int64
    every = torch.tensor([[(p >> i) & 1 for i in range(4)] for p in range(16)])
    assert proximity_pattern(every).tolist() == list(range(16))
    assert proximity_pattern(torch.zeros(2, 3, 4, dtype=torch.bool)).shape == (2, 3)


def test_qlearning_state_is_cell_times_sixteen_plus_pattern():
    cell = torch.tensor([0, 1, 99])
    sensors = torch.tensor([[True, True, False, False], [False] * 4, [False, False, True, True]])
    # 0 * 16 + 3 = 3; 1 * 16 + 0 = 16; 99 * 16 + (4 + 8) = 1596
    assert qlearning_state(cell, sensors).tolist() == [3, 16, 1596]


def test_qlearning_state_of_the_env_observation_covers_the_1600_states_range():
    env = FactoredGridEnv(batch_size=(32,), obstacle_period=1)
    torch.manual_seed(0)
    data = env.rollout(50, break_when_any_done=False)
    states = qlearning_state(data["cell"], data["proximity"])
    assert states.shape == (32, 50)
    assert bool(((states >= 0) & (states < 1600)).all())
    assert torch.equal(states // 16, data["cell"])


# --- keep_reward: the recipe's reward untouched, local_reward beside it (issue 26) ----------


def test_keep_reward_leaves_the_conventional_reward_and_adds_the_collision_vector():
    settings = dict(size=5, num_obstacles=6, obstacle_period=1, batch_size=(3,))
    plain = FactoredGridEnv(**settings, seed=4)
    kept = TransformedEnv(FactoredGridEnv(**settings, seed=4), SplitLocalReward(keep_reward=True))
    torch.manual_seed(0)
    actions = torch.randint(0, 4, (40, 3))
    td_plain, td_kept = plain.reset(), kept.reset()
    assert td_kept["local_reward"].tolist() == [[0.0] * 4] * 3  # an observation from the reset
    for action in actions:
        td_plain = plain.step(td_plain.set("action", action))
        td_kept = kept.step(td_kept.set("action", action))
        assert torch.equal(td_kept["next", "reward"], td_plain["next", "reward"])
        assert torch.equal(td_kept["next", "local_reward"], td_plain["next", "collision"])
        td_plain, td_kept = step_mdp(td_plain), step_mdp(td_kept)


def test_keep_reward_keeps_env_reward_key_and_passes_check_env_specs():
    from torchrl.envs import Compose, RewardSum, StepCounter

    env = TransformedEnv(
        FactoredGridEnv(size=4, num_obstacles=2, batch_size=(2,)),
        Compose(SplitLocalReward(keep_reward=True), StepCounter(), RewardSum()),
    )
    assert env.reward_key == "reward"  # local_reward is no second reward
    assert "local_reward" in env.observation_spec.keys()
    check_env_specs(env)
    split = split_env(size=4, num_obstacles=2)
    with pytest.raises(KeyError):  # the Factor-Q split declares two rewards (documented)
        _ = split.reward_key


def test_keep_reward_must_be_a_bool():
    with pytest.raises(TypeError, match="keep_reward"):
        SplitLocalReward(keep_reward="yes")
