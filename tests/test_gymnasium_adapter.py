"""The Gymnasium adapter (issue 25): a declaration read against a hand-checked env, Gymnasium's
and torchrl's own checkers, the batched torchrl env, and one clear error per bad input.

The env under test is gymnasium's own ``FrozenLake-v1`` (4x4, not slippery: deterministic, so
every expected value is worked out by hand from its map ``SFFF / FHFH / FFFH / HFFG``): the
declared collision is falling into a hole, the sensors are the holes around the agent.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv, make_registered, require_extra
from factorq_envs.protocol import CONFIG_FIELDS
from factorq_torch.base import keys

LAKE = ("SFFF", "FHFH", "FFFH", "HFFG")
#: FrozenLake's actions: 0 left, 1 down, 2 right, 3 up; (row, col) moves.
MOVES = ((0, -1), (1, 0), (0, 1), (-1, 0))


def _hole(row: int, col: int) -> bool:
    return 0 <= row < 4 and 0 <= col < 4 and LAKE[row][col] == "H"


def hole_sensors(observation, info, env) -> np.ndarray:
    """One sensor per action: a hole in that direction (off the map is no hole)."""
    row, col = divmod(int(observation), 4)
    return np.array([_hole(row + dr, col + dc) for dr, dc in MOVES])


def fell(reward: float, info: dict) -> bool:
    return bool(info.get("fell", False))


class MarkHoles(gymnasium.Wrapper, gymnasium.utils.RecordConstructorArgs):
    """FrozenLake's info says nothing about holes: this puts ``fell`` in it (the user's side)."""

    def __init__(self, env):
        gymnasium.utils.RecordConstructorArgs.__init__(self)
        gymnasium.Wrapper.__init__(self, env)

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        row, col = divmod(int(observation), 4)
        return observation, reward, terminated, truncated, dict(info, fell=LAKE[row][col] == "H")


DECLARATION = Declaration(
    num_sensors=4,
    sensors=hole_sensors,
    collision=fell,
    actuator_names=("left", "down", "right", "up"),
    task_state=lambda observation, info, env: int(observation),
    num_cells=16,
    dependency=tuple(tuple(a == k for k in range(4)) for a in range(4)),
)


def make_lake(seed: int | None = None, declaration: Declaration = DECLARATION) -> FactorQEnv:
    env = MarkHoles(gymnasium.make("FrozenLake-v1", is_slippery=False))
    return FactorQEnv(env, declaration, seed=seed)


def test_a_hand_worked_episode():
    """From the start (cell 0): right to 1 (hole below it), down into the hole at 5: collision
    charged to 'down', task reward 0 + the default penalty put back, episode over."""
    env = make_lake()
    observation, info = env.reset(seed=0)
    assert observation[keys.CELL] == 0 and observation[keys.SENSORS].tolist() == [0, 0, 0, 0]
    assert info["collided"] is False
    observation, reward, terminated, _, info = env.step(2)  # right: cell 1
    assert observation[keys.CELL] == 1
    assert observation[keys.SENSORS].tolist() == [0, 1, 0, 0]  # the hole at 5 is below
    assert observation[keys.COLLISION].tolist() == [0.0] * 4 and not terminated
    observation, reward, terminated, _, info = env.step(1)  # down: into the hole
    assert terminated and info["collided"] is True
    assert observation[keys.BUMP].tolist() == [0, 1, 0, 0]
    assert observation[keys.COLLISION].tolist() == [0.0, -1.0, 0.0, 0.0]
    assert reward == 0.0  # the conventional reward is FrozenLake's own
    assert info["task_reward"] == 1.0  # its reward without the collision's part (default)
    assert observation["observation"] == 5  # the env's own observation passes through


def test_a_declared_task_reward_and_charge():
    """A declared task reward is returned with the collision vector added; ``charge`` picks the
    actuator that pays."""
    declaration = Declaration(
        num_sensors=4,
        sensors=hole_sensors,
        collision=fell,
        task_reward=lambda reward, info: 10.0 * reward,
        charge=lambda actuator, info: 0,
        penalty=2.0,
    )
    env = make_lake(declaration=declaration)
    env.reset(seed=0)
    env.step(2)
    observation, reward, *_ = env.step(1)
    assert observation[keys.COLLISION].tolist() == [-2.0, 0.0, 0.0, 0.0]
    assert reward == 0.0 - 2.0
    env.reset(seed=0)
    for action in (2, 2, 1, 1, 1, 2):  # 1, 2, 6, 10, 14, 15: around the holes to the goal
        observation, reward, terminated, _, info = env.step(action)
    assert terminated and reward == 10.0 and info["task_reward"] == 10.0


def test_gymnasium_check_env_and_spec():
    env = make_lake(seed=3)
    check_env(env, skip_render_check=True)
    spec = env.spec  # RecordConstructorArgs: the wrapper can be re-created from its spec
    assert spec.additional_wrappers[-1].name == "FactorQEnv"


def test_sizes_share_one_interface():
    """``env.config`` answers every CONFIG_FIELD on the adapter, the torchrl grid env and the
    gymnasium grid env alike."""
    from factorq_envs import FactoredGridEnv
    from factorq_envs.gymnasium_env import FactoredGridGym

    for env in (
        make_lake(),
        FactoredGridEnv(size=3, num_obstacles=0),
        FactoredGridGym(size=3, num_obstacles=0),
    ):
        for field in CONFIG_FIELDS:
            assert hasattr(env.config, field), (type(env).__name__, field)
    config = make_lake().config
    assert (config.num_cells, config.num_sensors, config.num_actuators) == (16, 4, 4)
    assert config.actuator_names == ("left", "down", "right", "up")
    assert config.max_steps == 100  # FrozenLake's registered TimeLimit


def test_first_reset_uses_the_seed():
    env = FactorQEnv(gymnasium.make("CartPole-v1"), _cartpole_declaration(), seed=7)
    first, _ = env.reset()
    again, _ = gymnasium.make("CartPole-v1").reset(seed=7)
    assert np.array_equal(first["observation"], again)


def _cartpole_declaration() -> Declaration:
    return Declaration(
        num_sensors=1,
        sensors=lambda obs, info, env: np.array([obs[2] > 0]),
        collision=lambda reward, info: False,
    )


@pytest.mark.parametrize("backend", ["sync", "async", "parallel"])
def test_torchrl_env_has_the_project_keys_and_passes_check_env_specs(backend):
    """S adapters as one torchrl env: categorical cell, bool sensors, the split reward and the
    tables work on it; partial resets restart only the marked envs."""
    from torchrl.envs import TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from factorq_envs.declared_env import declared_torchrl_env
    from factorq_envs.transforms import SplitLocalReward
    from factorq_torch.tables import LocalRewardTable

    base = declared_torchrl_env(make_lake, [0, 1, 2], backend=backend)
    try:
        env = TransformedEnv(base, SplitLocalReward())
        check_env_specs(env)
        td = env.reset()
        assert td[keys.CELL].tolist() == [0, 0, 0] and td[keys.CELL].dtype == torch.int64
        assert td[keys.SENSORS].dtype == torch.bool and td[keys.SENSORS].shape == (3, 4)
        td["action"] = torch.tensor([2, 1, 1])  # right; down; down
        td = env.step(td)
        assert td["next", keys.CELL].tolist() == [1, 4, 4]
        td = env.step_mdp(td)
        td["action"] = torch.tensor([1, 2, 1])  # 1 -> hole 5; 4 -> hole 5; 4 -> 8
        td = env.step(td)
        nxt = td["next"]
        assert nxt["local_reward"].tolist() == [[0, -1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 0]]
        assert nxt["terminated"].reshape(-1).tolist() == [True, True, False]
        table = LocalRewardTable(3, dependency=base.dependency)
        table.update_running_mean(nxt[keys.SENSORS], td["action"], nxt["local_reward"])
        assert base.config.num_sensors == 4 and base.dependency.shape == (4, 4)
        partial = env.step_mdp(td)
        partial["_reset"] = torch.tensor([[True], [False], [False]])
        after = env.reset(partial)
        assert after[keys.CELL].tolist() == [0, 5, 8]
    finally:
        base.close()


def test_highway_style_info_key_collision():
    """``collision`` may name an info key; a key the env's info lacks is refused at
    construction (the probe), naming the key and what the info has."""
    declaration = Declaration(
        num_sensors=1,
        sensors=lambda obs, info, env: np.array([False]),
        collision="crashed",
    )
    with pytest.raises(KeyError, match=r"collision read the key 'crashed'.*info has \[\]"):
        FactorQEnv(gymnasium.make("CartPole-v1"), declaration)


@pytest.mark.parametrize(
    "sensors, message",
    [
        (lambda obs, info, env: np.array([True, False]), r"\[1\] bool, got shape \(2,\)"),
        (lambda obs, info, env: np.array([1]), r"\[1\] bool, got shape \(1,\) dtype int64"),
        (lambda obs, info, env: info["missing"], r"sensors read the key 'missing'"),
    ],
)
def test_a_bad_sensors_function_is_refused_at_construction(sensors, message):
    declaration = Declaration(num_sensors=1, sensors=sensors, collision=lambda reward, info: False)
    with pytest.raises((ValueError, KeyError), match=message):
        FactorQEnv(gymnasium.make("CartPole-v1"), declaration)


def test_other_bad_input_names_the_problem():
    declaration = _cartpole_declaration()
    with pytest.raises(TypeError, match="Discrete action space.*Pendulum-v1.*Box"):
        FactorQEnv(gymnasium.make("Pendulum-v1"), declaration)
    with pytest.raises(ValueError, match="'NoSuchEnv-v0' is not registered"):
        make_registered("NoSuchEnv-v0")
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'factorq-torch\[nothing\]'"):
        require_extra("no_such_module_here", "factorq-torch[nothing]")
    with pytest.raises(ValueError, match="dependency has 3 rows for 2 actuators"):
        FactorQEnv(
            gymnasium.make("CartPole-v1"),
            Declaration(
                num_sensors=1,
                sensors=declaration.sensors,
                collision=declaration.collision,
                dependency=((True,),) * 3,
            ),
        )
    with pytest.raises(ValueError, match="Declaration.actions \\[5\\]"):
        FactorQEnv(
            gymnasium.make("CartPole-v1"),
            Declaration(num_sensors=1, sensors=declaration.sensors, collision=fell, actions=(0, 5)),
        )
    with pytest.raises(TypeError, match="Declaration.collision must be callable"):
        Declaration(num_sensors=1, sensors=declaration.sensors, collision=3)
    with pytest.raises(ValueError, match="task_state returned cell=16"):
        make_lake(
            declaration=Declaration(
                num_sensors=4,
                sensors=hole_sensors,
                collision=fell,
                task_state=lambda observation, info, env: 16,
                num_cells=16,
            )
        )


def test_the_experiment_command_at_a_tiny_budget(tmp_path):
    """``trainers/experiments/gym.py`` follows the command protocol: units per (method, seed),
    deterministic ``run_unit``, a summary, the report and the figure (MiniGrid 8x8: fast)."""
    pytest.importorskip("minigrid")
    from factorq_trainers.experiments import gym as experiment
    from factorq_trainers.reports import gym as report_module

    config = experiment.GymConfig(
        world="minigrid-8x8", seeds=1, steps=40, eval_episodes=1, curve_points=4
    )
    units = experiment.units(config)
    assert [u["id"] for u in units] == [f"{m}-seed0" for m in experiment.DEFAULT_METHODS]
    results = [experiment.run_unit(config, unit) for unit in units]
    again = experiment.run_unit(config, units[1])  # factor-q-oracle, seed 0
    assert again["curve_crashes"] == results[1]["curve_crashes"]
    assert again["greedy_return"] == results[1]["greedy_return"]
    for result in results:
        assert result["curve_steps"] == [10, 20, 30, 40]
        assert result["crashes_per_1000"] == 1000 * result["crashes"] / 40
    summary = experiment.summarise(config, results)
    summary["config"] = {"seeds": 1, "steps": 40, "eval_episodes": 1, "window": 5}
    report = report_module.markdown(summary)
    assert "| neural Factor-Q, oracle dependency |" in report
    report_module.figure(summary, tmp_path / "gym.png")
    assert (tmp_path / "gym.png").stat().st_size > 0
    with pytest.raises(ValueError, match="world='atari'"):
        experiment.GymConfig(world="atari")


def test_the_experiment_summary_keeps_its_intervals_inside_the_possible_range():
    """``factorq gym``'s summary over 3 seeds: Wilson's interval for the greedy crash rate (hand
    computed: p = 1/15, n = 3, z = 1.96), the BCa bootstrap for the other measures and the
    curves' bands, each inside [min, max] of the seeds (a t interval went below 0 for these)."""
    from factorq_trainers.experiments import gym as experiment

    config = experiment.GymConfig(world="minigrid-8x8", seeds=3, methods=("dqn",), steps=30)
    per_seed = [
        (0.0, 0.0, None, [None, 1.0, 2.0]),
        (10.0, 0.0, 300, [None, None, 4.0]),
        (50.0, 0.2, 500, [0.5, 1.5, 3.0]),
    ]
    results = [
        {
            "crashes_per_1000": crashes,
            "greedy_crash_rate": rate,
            "greedy_return": 1.0,
            "steps_to_threshold": reached,
            "steps_per_s": 100.0 + crashes,
            "curve_steps": [10, 20, 30],
            "curve_crashes": [0, int(crashes) // 2, int(crashes)],
            "curve_return": curve,
            "wall_s": 1.0,
        }
        for crashes, rate, reached, curve in per_seed
    ]
    entry = experiment.summarise(config, results)["methods"]["dqn"]
    rate = entry["greedy_crash_rate"]
    assert rate["mean"] == pytest.approx(1 / 15)
    assert rate["ci95"] == pytest.approx([0.0031597, 0.6168044], abs=1e-6)
    crashes = entry["crashes_per_1000"]
    assert crashes["mean"] == pytest.approx(20.0)
    assert 0.0 <= crashes["ci95"][0] < 20.0 < crashes["ci95"][1] <= 50.0
    reached = entry["steps_to_threshold"]
    assert (reached["mean"], reached["n"]) == (400.0, 2)
    assert 300 <= reached["ci95"][0] < 400 < reached["ci95"][1] <= 500
    assert entry["greedy_return"] == {"mean": 1.0, "ci95": [1.0, 1.0], "n": 3}  # all seeds equal
    band = entry["bands"]["curve_return"]
    assert band["mean"] == pytest.approx([0.5, 1.25, 3.0])
    assert band["low"][0] is None and band["high"][0] is None  # one seed: no band
    assert 1.0 <= band["low"][1] < 1.25 < band["high"][1] <= 1.5
    assert 2.0 <= band["low"][2] < 3.0 < band["high"][2] <= 4.0
    assert entry["bands"]["curve_crashes"]["low"][0] == 0.0  # every seed at 0: the band is 0


@pytest.mark.parametrize("backend", ["sync", "async"])
def test_a_maker_that_returns_no_adapter_is_refused(backend):
    """``make_env`` must return a ``FactorQEnv``: a bare Gymnasium env gets one clear error."""
    from factorq_envs.declared_env import declared_torchrl_env

    with pytest.raises(TypeError, match=r"must return a FactorQEnv \(.*\), got TimeLimit"):
        declared_torchrl_env(_bare_lake, [0], backend=backend)


def _bare_lake(seed: int) -> gymnasium.Env:
    return gymnasium.make("FrozenLake-v1")


def test_a_partial_step_is_refused():
    """A vector env steps all its envs: a '_step' mask is refused, not silently ignored."""
    from factorq_envs.declared_env import declared_torchrl_env

    env = declared_torchrl_env(make_lake, [0, 1])
    td = env.reset()
    td["action"] = torch.tensor([2, 2])
    td["_step"] = torch.tensor([[True], [False]])
    with pytest.raises(NotImplementedError, match="'_step' mask"):
        env.step(td)


def test_the_gym_command_takes_risk_aware_exploration_for_neural_factor_q():
    # issue 39: neural Factor-Q explores among the actuators not called risky; DQN is untouched
    pytest.importorskip("minigrid")
    from factorq_trainers.experiments import gym as experiment

    options = dict(world="minigrid-8x8", seeds=1, steps=40, eval_episodes=1, curve_points=4)
    unit = {"id": "factor-q-oracle-seed0", "method": "factor-q-oracle", "seed_index": 0}
    careful = experiment.run_unit(experiment.GymConfig(**options, exploration="risk-aware"), unit)
    assert careful["curve_steps"] == [10, 20, 30, 40]
    with pytest.raises(ValueError, match="exploration='careful' is unknown"):
        experiment.GymConfig(**options, exploration="careful")
