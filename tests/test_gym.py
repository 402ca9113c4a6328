"""The gymnasium env (envs/gymnasium_env.py): API checks and the same world as the torchrl env."""

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from torchrl.envs.utils import step_mdp

import factorq_envs  # noqa: F401  (registers "FactoredGrid-v0")
from factorq_envs import FactoredGridEnv
from factorq_envs.gymnasium_env import FactoredGridGym


@pytest.mark.parametrize("obstacle_period", [0, 10, 1])
def test_gymnasium_check_env_passes(obstacle_period):
    env = gymnasium.make("FactoredGrid-v0", obstacle_period=obstacle_period, render_mode="ansi")
    check_env(env.unwrapped)


def test_make_passes_keywords_and_builds_the_spaces():
    env = gymnasium.make("FactoredGrid-v0", size=5, num_obstacles=3, obstacle_period=1)
    space = env.observation_space
    assert isinstance(space, gymnasium.spaces.Dict)
    assert space["cell"] == gymnasium.spaces.Discrete(25)
    assert space["proximity"] == gymnasium.spaces.MultiBinary(4)
    assert space["bump"] == gymnasium.spaces.MultiBinary(4)
    assert env.action_space == gymnasium.spaces.Discrete(4)
    observation, info = env.reset(seed=0)
    assert observation in space
    # the step's info keys, zero at a reset (torchrl's info_dict_reader reads both alike)
    assert info["local_reward"].tolist() == [0.0] * 4 and info["task_reward"] == 0.0
    assert env.unwrapped.obstacle_map().sum() == 3


def test_info_holds_the_local_reward_vector_and_the_task_reward():
    env = gymnasium.make("FactoredGrid-v0", size=2, num_obstacles=0)
    env.reset(seed=1)
    _, reward, terminated, truncated, info = env.step(1)  # west: the wall
    assert reward == -2.0 and not terminated and not truncated
    assert info["local_reward"].dtype == np.float32
    assert info["local_reward"].tolist() == [0.0, -1.0, 0.0, 0.0]
    assert info["task_reward"] == -1.0
    env.step(3)  # east
    observation, reward, terminated, truncated, info = env.step(2)  # south: the goal
    assert terminated and not truncated
    assert reward == 0.0 and info["task_reward"] == 0.0
    assert info["local_reward"].tolist() == [0.0] * 4
    assert int(observation["cell"]) == 3


def test_episode_is_truncated_after_max_steps():
    env = gymnasium.make("FactoredGrid-v0", size=3, num_obstacles=0, max_steps=2)
    env.reset(seed=0)
    assert env.step(0)[3] is False
    _, _, terminated, truncated, _ = env.step(0)
    assert truncated is True and terminated is False


def same_obstacles(gym_env, torch_env) -> bool:
    return np.array_equal(gym_env.unwrapped.obstacle_map(), torch_env.obstacle_map().numpy())


@pytest.mark.parametrize("obstacle_period", [0, 10, 1])
def test_gym_env_follows_the_torchrl_env_for_the_same_seed_and_actions(obstacle_period):
    settings = dict(size=5, num_obstacles=5, obstacle_period=obstacle_period, max_steps=15)
    gym_env = gymnasium.make("FactoredGrid-v0", **settings)
    torch_env = FactoredGridEnv(**settings, seed=21)
    observation, _ = gym_env.reset(seed=21)
    td = torch_env.reset()
    rng = np.random.default_rng(0)
    episodes = 0
    for _ in range(150):
        action = int(rng.integers(4))
        observation, reward, terminated, truncated, info = gym_env.step(action)
        td["action"] = torch.tensor(action)
        td = torch_env.step(td)
        nxt = td["next"]
        assert int(observation["cell"]) == nxt["cell"].item()
        assert observation["proximity"].tolist() == nxt["proximity"].int().tolist()
        assert observation["bump"].tolist() == nxt["bump"].int().tolist()
        assert reward == nxt["reward"].item()
        assert info["local_reward"].tolist() == nxt["collision"].tolist()
        assert observation["collision"].tolist() == nxt["collision"].tolist()
        assert (terminated, truncated) == (nxt["terminated"].item(), nxt["truncated"].item())
        assert same_obstacles(gym_env, torch_env)
        td = step_mdp(td)
        if terminated or truncated:
            episodes += 1
            observation, _ = gym_env.reset()
            td = torch_env.reset()
            assert int(observation["cell"]) == td["cell"].item() == 0
            assert np.array_equal(
                gym_env.unwrapped.obstacle_map(), torch_env.obstacle_map().numpy()
            )
    assert episodes >= 3


def test_reset_with_the_same_seed_replays_and_other_seeds_differ():
    env = gymnasium.make("FactoredGrid-v0", obstacle_period=1)
    maps = []
    for seed in (5, 5, 6):
        env.reset(seed=seed)
        env.step(2)
        maps.append(env.unwrapped.obstacle_map())
    assert np.array_equal(maps[0], maps[1])
    assert not np.array_equal(maps[0], maps[2])


def test_observations_are_new_arrays_every_step():
    env = gymnasium.make("FactoredGrid-v0")
    first, _ = env.reset(seed=0)
    second, *_ = env.step(0)
    assert first["proximity"] is not second["proximity"]
    first["bump"][:] = 1
    assert second["bump"].tolist() == [1, 0, 0, 0]


def test_render_ansi_shows_the_world_and_no_mode_renders_nothing():
    env = gymnasium.make("FactoredGrid-v0", size=3, num_obstacles=1, render_mode="ansi")
    env.reset(seed=0)
    picture = env.render()
    assert picture.splitlines()[1].startswith("#A") and picture.count("o") == 1
    assert "G" in picture.splitlines()[3]
    assert FactoredGridGym().render() is None


@pytest.mark.parametrize(
    "action, error, message",
    [
        (4, ValueError, r"action=4 .*\[0, 3\]"),
        (-1, ValueError, r"action=-1 .*\[0, 3\]"),
        (1.0, TypeError, r"action must be an int"),
        (True, TypeError, r"action must be an int"),
        (np.array([1, 2]), TypeError, r"action must be an int"),
    ],
)
def test_bad_action_raises_one_error_naming_it(action, error, message):
    env = FactoredGridGym()
    env.reset(seed=0)
    with pytest.raises(error, match=message):
        env.step(action)


def test_numpy_integer_actions_are_accepted():
    env = FactoredGridGym(size=3, num_obstacles=0)
    env.reset(seed=0)
    assert int(env.step(np.int64(3))[0]["cell"]) == 1
    assert int(env.step(np.array(2))[0]["cell"]) == 4


@pytest.mark.parametrize(
    "kwargs, error, message",
    [
        (dict(size=1), ValueError, r"size=1"),
        (dict(num_obstacles=200), ValueError, r"num_obstacles=200"),
        (dict(obstacle_period=-2), ValueError, r"obstacle_period=-2"),
        (dict(max_steps=0), ValueError, r"max_steps=0"),
        (dict(render_mode="human"), ValueError, r"render_mode='human'"),
    ],
)
def test_bad_constructor_argument_raises_naming_it(kwargs, error, message):
    with pytest.raises(error, match=message):
        FactoredGridGym(**kwargs)


def test_torchrl_gym_env_composes_with_split_local_reward_and_the_tables():
    """torchrl's own GymEnv of "FactoredGrid-v0" feeds the project's agent: categorical cell,
    bool sensors (no transform: factorq_envs.gym_spaces), the collision observation split by
    SplitLocalReward, the task reward read from info with its declared spec; the split equals the
    world's own."""
    from torchrl.envs import GymEnv, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from factorq_envs.gymnasium_env import torchrl_info_reader
    from factorq_envs.transforms import SplitLocalReward
    from factorq_torch.tables import TaskQTable

    env = GymEnv("FactoredGrid-v0", size=3, num_obstacles=0, categorical_action_encoding=True)
    env.set_info_dict_reader(torchrl_info_reader())
    env = TransformedEnv(env, SplitLocalReward())
    check_env_specs(env)
    td = env.reset()
    assert td["cell"].dtype == torch.int64 and td["cell"].shape == ()
    assert td["sensors"].dtype == torch.bool
    td["action"] = torch.tensor(0)  # north, into the wall
    nxt = env.step(td)["next"]
    assert nxt["local_reward"].tolist() == [-1.0, 0.0, 0.0, 0.0]
    assert nxt["reward"].tolist() == [-1.0] == [nxt["task_reward"].item()]
    table = TaskQTable(1, 9)
    assert table(nxt.unsqueeze(0).clone())["action_value"].shape == (1, 4)
