"""highway-fast-v0 as a declared world (issue 25): a hand-placed vehicle read by the sensors and
met as a crash charged to the chosen action, the oracle as data, Gymnasium's and torchrl's
checkers. Skips without the extra ``factorq-torch[highway]`` (CI installs it), except the
missing-extra message.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from factorq_envs import highway
from factorq_torch.base import keys


def test_missing_extra_names_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "highway_env", None)  # import fails, as uninstalled
    with pytest.raises(ModuleNotFoundError, match=r"pip install 'factorq-torch\[highway\]'"):
        highway.make_highway(seed=0)


def test_the_oracle_is_data():
    assert highway.SENSOR_NAMES == (
        "left<1s", "left<3s", "front<1s", "front<3s", "right<1s", "right<3s"
    )  # fmt: skip
    oracle = np.array(highway.ORACLE)
    assert oracle.shape == (5, 6)
    assert oracle[0].tolist() == [1, 1, 0, 0, 0, 0]  # LANE_LEFT <- the left lane
    assert oracle[2].tolist() == [0, 0, 0, 0, 1, 1]  # LANE_RIGHT <- the right lane
    assert oracle[4].tolist() == [0, 0, 1, 0, 0, 0]  # SLOWER <- a vehicle within 1 s ahead


def _alone_with_one_vehicle(env, gap: float, speed: float):
    """The ego vehicle and one other vehicle ``gap`` m ahead in its lane at ``speed``."""
    base = env.unwrapped
    ego, other = base.vehicle, next(v for v in base.road.vehicles if v is not base.vehicle)
    base.road.vehicles = [ego, other]
    longitudinal = ego.lane.local_coordinates(ego.position)[0]
    other.lane_index = other.target_lane_index = ego.lane_index
    other.lane = ego.lane
    other.position = ego.lane.position(longitudinal + gap, 0)
    other.heading = ego.heading
    other.speed = other.target_speed = speed
    return ego


def _step_of(env):
    """The adapter's view of the env now, as the declared functions read it."""
    from factorq_envs.gymnasium_adapter import Transition

    return Transition(None, 0.0, False, False, {}, env.env)


def test_a_vehicle_ahead_is_sensed_then_hit_and_the_crash_charged_to_idle():
    """Ego at 25 m/s, a vehicle 8 m ahead at 15 m/s: time to collision 0.8 s (under 1 s, so
    front<1s and front<3s); IDLE for one second closes 10 m: a crash, charged to IDLE."""
    pytest.importorskip("highway_env")
    env = highway.make_highway(seed=0)
    env.reset(seed=0)
    ego = _alone_with_one_vehicle(env, gap=8.0, speed=15.0)
    assert ego.speed == 25.0
    sensors = highway.ttc_sensors(_step_of(env))
    names = [n for n, on in zip(highway.SENSOR_NAMES, sensors, strict=True) if on]
    assert "front<1s" in names and "front<3s" in names
    assert "left<1s" not in names  # nobody in the left lane (or no lane at all: see below)
    observation, reward, terminated, _, info = env.step(1)  # IDLE
    assert info["crashed"] and terminated
    assert observation[keys.COLLISION].tolist() == pytest.approx([0, -highway.PENALTY, 0, 0, 0])
    assert observation[keys.BUMP].tolist() == [0, 1, 0, 0, 0]
    # the conventional reward is highway's own; the task reward drops the crash's part
    assert info["task_reward"] == pytest.approx(reward + highway.PENALTY)


def test_a_far_vehicle_is_only_far():
    """The same vehicle 30 m ahead at 20 m/s: time to collision 6 s minus the car lengths'
    margin (5 m: 5 s at cost 0.5): neither within 1 s nor within 3 s."""
    pytest.importorskip("highway_env")
    env = highway.make_highway(seed=0)
    env.reset(seed=0)
    _alone_with_one_vehicle(env, gap=30.0, speed=20.0)
    sensors = dict(zip(highway.SENSOR_NAMES, highway.ttc_sensors(_step_of(env)), strict=True))
    assert not sensors["front<1s"] and not sensors["front<3s"]


def test_gymnasium_and_torchrl_checkers_accept_it():
    pytest.importorskip("highway_env")
    from gymnasium.utils.env_checker import check_env
    from torchrl.envs import TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from factorq_envs.declared_env import declared_torchrl_env
    from factorq_envs.transforms import SplitLocalReward

    env = highway.make_highway(seed=1)
    check_env(env, skip_render_check=True)
    assert env.config.actuator_names == highway.ACTUATOR_NAMES
    assert env.config.num_sensors == 6 and env.config.num_actuators == 5
    torchrl_env = declared_torchrl_env(highway.make_highway, [1, 2])
    check_env_specs(TransformedEnv(torchrl_env, SplitLocalReward()))
    td = torchrl_env.reset()
    assert (
        td["observation"].shape == (2, 5, 5) and td[keys.SENSORS].dtype.is_floating_point is False
    )
    assert torchrl_env.dependency.shape == (5, 6)


def test_the_paired_oracle_is_what_the_data_support():
    """``highway-pairs`` declares a lane change's crash by its target lane and the vehicle ahead
    within 1 s, IDLE and FASTER by the vehicle ahead within 1 s; SLOWER as the written oracle."""
    paired = dict(zip(highway.ACTUATOR_NAMES, np.array(highway.PAIRED_ORACLE), strict=True))
    names = np.array(highway.SENSOR_NAMES)
    assert list(names[paired["LANE_LEFT"]]) == ["left<1s", "front<1s"]
    assert list(names[paired["LANE_RIGHT"]]) == ["front<1s", "right<1s"]
    for action in ("IDLE", "FASTER", "SLOWER"):
        assert list(names[paired[action]]) == ["front<1s"]
    pytest.importorskip("highway_env")
    from factorq_envs.worlds import resolve_world

    env = resolve_world("highway-pairs").make(0)
    try:
        assert env.declaration.dependency == highway.PAIRED_ORACLE
    finally:
        env.close()
