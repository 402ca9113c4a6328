"""The Gymnasium adapter (issue 25): a declaration read against a hand-checked env, Gymnasium's
and torchrl's own checkers, the batched torchrl env, and one clear error per bad input.

The env under test is gymnasium's own ``FrozenLake-v1`` (4x4, not slippery: deterministic, so
every expected value is worked out by hand from its map ``SFFF / FHFH / FFFH / HFFG``): the
declared collision is falling into a hole, the sensors are the holes around the agent.
"""

from __future__ import annotations

import dataclasses
import functools

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


def hole_sensors(step) -> np.ndarray:
    """One sensor per action: a hole in that direction (off the map is no hole)."""
    row, col = divmod(int(step.observation), 4)
    return np.array([_hole(row + dr, col + dc) for dr, dc in MOVES])


def fell(step) -> bool:
    """FrozenLake's hole ends the episode with reward 0 (its goal with 1): read from the step."""
    return step.terminated and step.reward == 0


DECLARATION = Declaration(
    num_sensors=4,
    sensors=hole_sensors,
    collision=fell,
    task_reward=lambda step: step.reward,  # FrozenLake's reward holds no penalty
    actuator_names=("left", "down", "right", "up"),
    task_state=lambda step: step.observation,
    num_cells=16,
    dependency=tuple(tuple(a == k for k in range(4)) for a in range(4)),
)


def make_lake(seed: int | None = None, declaration: Declaration = DECLARATION) -> FactorQEnv:
    return FactorQEnv(gymnasium.make("FrozenLake-v1", is_slippery=False), declaration, seed=seed)


def test_a_hand_worked_episode():
    """From the start (cell 0): right to 1 (hole below it), down into the hole at 5: collision
    charged to 'down', task reward FrozenLake's 0, conventional reward 0 - 1, episode over; no
    wrapper: the hole is read from the step's ``terminated`` and reward."""
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
    assert info["task_reward"] == 0.0  # the declared task reward: FrozenLake's own
    assert reward == -1.0  # the conventional reward: task + collision
    assert observation["observation"] == 5  # the env's own observation passes through


def test_every_declared_function_reads_the_whole_step():
    """One ``Transition`` per reset and step: the env's own observation, reward, flags and info,
    the env inside the adapter and the chosen actuator (``None``, reward 0 at a reset)."""
    seen = []

    def sensors(step):
        seen.append(step)
        return hole_sensors(step)

    env = make_lake(declaration=dataclasses.replace(DECLARATION, sensors=sensors))
    seen.clear()  # the probe's reset and step
    env.reset(seed=0)
    env.step(2)  # right, to cell 1
    env.step(1)  # down, into the hole at 5
    reset, right, down = seen
    assert (reset.observation, reset.reward, reset.action) == (0, 0.0, None)
    assert (reset.terminated, reset.truncated) == (False, False) and reset.env is env.env
    assert (right.observation, right.reward, right.terminated, right.action) == (1, 0.0, False, 2)
    assert (down.observation, down.reward, down.terminated, down.truncated) == (5, 0.0, True, False)
    assert down.action == 1 and down.info == {"prob": 1.0}  # FrozenLake's own info
    with pytest.raises(dataclasses.FrozenInstanceError):
        down.reward = 1.0


def test_the_default_task_reward_never_pays_for_a_collision():
    """FrozenLake's hole is worth 0 and its goal 1: the default task reward (the env's reward +
    the penalty on a collision) would make a fall worth +1, the goal's reward. The adapter stops
    at the first fall (or at the probing step, when the probe falls) and names what to declare."""
    without = dataclasses.replace(DECLARATION, task_reward=None)
    env = make_lake(declaration=without)  # the probe (left, at the start) does not fall
    env.reset(seed=0)
    env.step(2)
    message = (
        r"FrozenLake-v1: a collision with the env's reward 0.0: the default task reward \(the "
        r"env's reward \+ penalty 1.0 = 1.0\) would pay for it.*Declare task_reward=lambda step: "
        r"step.reward"
    )
    with pytest.raises(ValueError, match=message):
        env.step(1)
    hole_on_the_left = gymnasium.make("FrozenLake-v1", desc=["HSFG"], is_slippery=False)
    with pytest.raises(ValueError, match=message):
        FactorQEnv(hole_on_the_left, without)  # the probe steps left, into the hole
    # an env whose reward holds the penalty keeps the default: the fall's -1 is the collision
    penalised = dataclasses.replace(without, collision=lambda step: step.reward < 0)
    env = FactorQEnv(_PenalisedLake(gymnasium.make("FrozenLake-v1", is_slippery=False)), penalised)
    env.reset(seed=0)
    env.step(2)
    observation, reward, terminated, _, info = env.step(1)
    assert (reward, info["task_reward"], terminated) == (-1.0, 0.0, True)
    assert observation[keys.COLLISION].tolist() == [0.0, -1.0, 0.0, 0.0]


class _PenalisedLake(gymnasium.Wrapper):
    """FrozenLake whose hole costs -1: an env whose reward holds the penalty."""

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        hole = terminated and reward == 0
        return observation, -1.0 if hole else reward, terminated, truncated, info


def test_a_declared_task_reward_and_charge():
    """A declared task reward is returned with the collision vector added; ``charge`` picks the
    actuator that pays."""
    declaration = Declaration(
        num_sensors=4,
        sensors=hole_sensors,
        collision=fell,
        task_reward=lambda step: 10.0 * step.reward,
        charge=lambda step: 0,
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
        sensors=lambda step: np.array([step.observation[2] > 0]),
        collision=lambda step: False,
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
        sensors=lambda step: np.array([False]),
        collision="crashed",
    )
    with pytest.raises(KeyError, match=r"collision read the key 'crashed'.*info has \[\]"):
        FactorQEnv(gymnasium.make("CartPole-v1"), declaration)


@pytest.mark.parametrize(
    "sensors, message",
    [
        (lambda step: np.array([True, False]), r"\[1\] bool, got shape \(2,\)"),
        (lambda step: np.array([1]), r"\[1\] bool, got shape \(1,\) dtype int64"),
        (lambda step: step.info["missing"], r"sensors read the key 'missing'"),
    ],
)
def test_a_bad_sensors_function_is_refused_at_construction(sensors, message):
    declaration = Declaration(num_sensors=1, sensors=sensors, collision=lambda step: False)
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
    with pytest.raises(
        ValueError, match=r"FrozenLake-v1: Declaration.task_state \(the cell\) returned 16"
    ):
        make_lake(
            declaration=Declaration(
                num_sensors=4,
                sensors=hole_sensors,
                collision=fell,
                task_state=lambda step: 16,
                num_cells=16,
            )
        )


def test_the_experiment_command_at_a_tiny_budget(tmp_path):
    """``trainers/commands/gym/command.py`` follows the command protocol: units per (method, seed),
    deterministic ``run_unit``, a summary, the report and the figure (MiniGrid 8x8: fast)."""
    pytest.importorskip("minigrid")
    from factorq_trainers.commands.gym import command as experiment
    from factorq_trainers.commands.gym import report as report_module
    from factorq_trainers.commands.gym.config import DEFAULT_METHODS

    config = experiment.GymConfig(
        world="minigrid-8x8", seeds=1, steps=40, eval_episodes=1, curve_points=4
    )
    units = experiment.units(config)
    assert [u["id"] for u in units] == [f"{m}-seed0" for m in DEFAULT_METHODS]
    results = [experiment.run_unit(config, unit) for unit in units]
    again = experiment.run_unit(config, units[1])  # factor-dqn, seed 0
    assert again["curve_crashes"] == results[1]["curve_crashes"]
    assert again["greedy_return"] == results[1]["greedy_return"]
    for result in results:
        assert result["curve_steps"] == [10, 20, 30, 40]
        assert result["crashes_per_1000"] == 1000 * result["crashes"] / 40
    summary = experiment.summarise(config, results)
    summary["config"] = {"seeds": 1, "steps": 40, "eval_episodes": 1, "window": 5}
    report = report_module.markdown(summary)
    assert "| neural Factor-Q |" in report
    report_module.figure(summary, tmp_path / "gym.png")
    assert (tmp_path / "gym.png").stat().st_size > 0
    with pytest.raises(
        ValueError,
        match="world 'atari' is unknown: choose one of highway, minigrid-5x5, minigrid-6x6, "
        "minigrid-8x8, minigrid-16x16",
    ):
        experiment.GymConfig(world="atari")


def test_the_experiment_summary_keeps_its_intervals_inside_the_possible_range():
    """``factorq gym``'s summary over 3 seeds: Wilson's interval for the greedy crash rate (hand
    computed: p = 1/15, n = 3, z = 1.96), the BCa bootstrap for the other measures and the
    curves' bands, each inside [min, max] of the seeds (a t interval went below 0 for these)."""
    from factorq_trainers.commands.gym import command as experiment

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


# -------------------------------------------------------------------------------------------
# Values at the library edge (issue 41): each refused in one line naming the env and the field


class _Altered(gymnasium.Wrapper):
    """CartPole whose reset or step returns are altered by ``reset_as`` / ``step_as``."""

    def __init__(self, reset_as=None, step_as=None):
        super().__init__(gymnasium.make("CartPole-v1"))
        self.reset_as, self.step_as = reset_as, step_as

    def reset(self, **kwargs):
        returned = self.env.reset(**kwargs)
        return returned if self.reset_as is None else self.reset_as(*returned)

    def step(self, action):
        returned = self.env.step(action)
        return returned if self.step_as is None else self.step_as(*returned)


def _pole(**fields) -> Declaration:
    fields.setdefault("sensors", lambda step: np.array([step.observation[2] > 0]))
    fields.setdefault("collision", lambda step: False)
    return Declaration(num_sensors=1, **fields)


@pytest.mark.parametrize(
    "env, declaration, error, message",
    [
        # declared values
        (
            None,
            _pole(sensors=lambda step: np.array([np.nan], np.float32), features=True),
            ValueError,
            r"CartPole-v1: Declaration.sensors returned features \[nan\]: every feature must be "
            r"finite",
        ),
        (
            None,
            _pole(sensors=lambda step: np.array([np.inf], np.float32), features=True),
            ValueError,
            r"CartPole-v1: Declaration.sensors returned features \[inf\]",
        ),
        (
            None,
            _pole(task_state=lambda step: 2.9, num_cells=4),
            TypeError,
            r"CartPole-v1: Declaration.task_state \(the cell\) returned 2.9 \(float\): must be an "
            r"int in \[0, 4\)",
        ),
        (
            None,
            _pole(task_state=lambda step: float("nan"), num_cells=4),
            TypeError,
            r"CartPole-v1: Declaration.task_state \(the cell\) returned nan",
        ),
        (
            None,
            _pole(task_state=lambda step: (1, 0.5), num_cells=4, num_headings=2),
            TypeError,
            r"CartPole-v1: Declaration.task_state \(the heading\) returned 0.5",
        ),
        (
            None,
            _pole(task_state=lambda step: 1, num_cells=4, num_headings=2),
            TypeError,
            r"CartPole-v1: Declaration.task_state returned 1: with num_headings=2 it must return "
            r"\(cell, heading\)",
        ),
        (
            None,
            _pole(collision=lambda step: float("nan")),
            TypeError,
            r"CartPole-v1: Declaration.collision returned nan \(float\): must be a bool",
        ),
        (
            None,
            _pole(collision=lambda step: "yes"),
            TypeError,
            r"CartPole-v1: Declaration.collision returned 'yes' \(str\): must be a bool",
        ),
        (
            _Altered(step_as=lambda o, r, te, tr, i: (o, r, te, tr, dict(i, hit=1))),
            _pole(collision="hit"),
            TypeError,
            r"CartPole-v1: Declaration.collision \(info\['hit'\]\) returned 1 \(int\): must be a "
            r"bool",
        ),
        (
            None,
            _pole(collision=lambda step: True, charge=lambda step: 1.7, task_reward=lambda s: 0.0),
            TypeError,
            r"CartPole-v1: Declaration.charge returned 1.7 \(float\): must be an int in \[0, 2\)",
        ),
        (
            None,
            _pole(collision=lambda step: True, charge=lambda step: None, task_reward=lambda s: 0.0),
            TypeError,
            r"CartPole-v1: Declaration.charge returned None \(NoneType\)",
        ),
        (
            None,
            _pole(collision=lambda step: True, charge=lambda step: 2, task_reward=lambda s: 0.0),
            ValueError,
            r"CartPole-v1: Declaration.charge returned 2: must be in \[0, 2\)",
        ),
        (
            None,
            _pole(task_reward=lambda step: float("nan")),
            ValueError,
            r"CartPole-v1: Declaration.task_reward's result is nan: must be finite",
        ),
        (
            None,
            _pole(task_reward=lambda step: "1"),
            TypeError,
            r"CartPole-v1: Declaration.task_reward's result must be a finite number, got '1'",
        ),
        # the env's own returns
        (
            _Altered(step_as=lambda o, r, te, tr, i: (o, float("nan"), te, tr, i)),
            _pole(),
            ValueError,
            r"CartPole-v1: the env's reward is nan: must be finite",
        ),
        (
            _Altered(step_as=lambda o, r, te, tr, i: (o, -np.inf, te, tr, i)),
            _pole(),
            ValueError,
            r"CartPole-v1: the env's reward is -inf: must be finite",
        ),
        (
            _Altered(reset_as=lambda o, i: o),
            _pole(),
            TypeError,
            r"CartPole-v1: reset\(\) returned ndarray .*: a Gymnasium env's reset returns "
            r"\(observation, info\)",
        ),
        (
            _Altered(reset_as=lambda o, i: (o, None)),
            _pole(),
            TypeError,
            r"CartPole-v1: reset\(\) returned info=None \(NoneType\): must be a dict",
        ),
        (
            _Altered(step_as=lambda o, r, te, tr, i: (o, r, te or tr, i)),
            _pole(),
            TypeError,
            r"CartPole-v1: step\(\) returned a tuple of 4: a Gymnasium env's step returns "
            r"\(observation, reward, terminated, truncated, info\)",
        ),
        (
            _Altered(step_as=lambda o, r, te, tr, i: (o, r, "no", tr, i)),
            _pole(),
            TypeError,
            r"CartPole-v1: step\(\) returned terminated='no' \(str\): must be a bool",
        ),
    ],
)
def test_a_bad_value_is_refused_naming_the_env_and_the_field(env, declaration, error, message):
    with pytest.raises(error, match=message):
        FactorQEnv(env or gymnasium.make("CartPole-v1"), declaration)


def test_bad_declared_numbers_are_refused_where_they_are_written():
    sensors = _pole().sensors
    with pytest.raises(TypeError, match=r"Declaration.penalty must be a number, got '1' \(str\)"):
        Declaration(num_sensors=1, sensors=sensors, collision="hit", penalty="1")
    with pytest.raises(TypeError, match=r"Declaration.actions\[0\] must be an int, got 1.9"):
        Declaration(num_sensors=1, sensors=sensors, collision="hit", actions=(1.9, 0))
    with pytest.raises(TypeError, match="Declaration.features must be a bool"):
        Declaration(num_sensors=1, sensors=sensors, collision="hit", features="yes")


@pytest.mark.parametrize("field", ["sensors", "collision", "charge", "task_state", "task_reward"])
def test_a_function_of_the_old_positional_form_is_refused_where_it_is_declared(field):
    fields = {"num_sensors": 1, "sensors": _pole().sensors, "collision": "hit"}
    fields[field] = lambda observation, info, env: 0
    signature = r"\(observation, info, env\)"
    with pytest.raises(
        TypeError, match=rf"Declaration.{field} must take one argument, the step .* {signature}"
    ):
        Declaration(**fields)
    # one argument, a partial of one and a default after it are all callable with the step
    for function in (lambda step, extra=1: 0, functools.partial(lambda size, step: 0, 3)):
        fields[field] = function
        Declaration(**fields)


def test_a_float_action_is_refused_naming_the_env():
    env = FactorQEnv(gymnasium.make("CartPole-v1"), _pole())
    env.reset(seed=0)
    for action in (1.9, np.float64(1.9), np.array(1.9), True):
        with pytest.raises(TypeError, match=r"CartPole-v1: action must be an int in \[0, 1\]"):
            env.step(action)


def test_the_gym_command_takes_risk_aware_exploration_for_neural_factor_q():
    # issue 39: neural Factor-Q explores among the actuators not called risky; DQN is untouched
    pytest.importorskip("minigrid")
    from factorq_trainers.commands.gym import command as experiment

    options = dict(world="minigrid-8x8", seeds=1, steps=40, eval_episodes=1, curve_points=4)
    unit = {"id": "factor-dqn-seed0", "method": "factor-dqn", "seed_index": 0}
    careful = experiment.run_unit(experiment.GymConfig(**options, exploration="risk-aware"), unit)
    assert careful["curve_steps"] == [10, 20, 30, 40]
    with pytest.raises(ValueError, match="exploration='careful' is unknown"):
        experiment.GymConfig(**options, exploration="careful")
