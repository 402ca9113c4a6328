"""highway-env's ``highway-fast-v0`` as a declared world: a dynamic world nobody here
wrote, read through the Gymnasium adapter (``factorq_envs.gymnasium_adapter``).

highway-env (Farama, ``highway-env`` 1.12.1, the optional extra ``factorq-torch[highway]``) is
stepped as it is. ``highway-fast-v0``: 3 lanes, 20 other vehicles, 30 s episodes at one decision
a second (``policy_frequency`` 1), the ego vehicle's meta-actions ``LANE_LEFT, IDLE, LANE_RIGHT,
FASTER, SLOWER`` (highway's own ``DiscreteMetaAction`` order: the actuators are its actions). An
episode ends (``terminated``) when the ego vehicle crashes.

**Two observation types.** The agent's task values read highway's ``Kinematics`` observation
(the env's own, ``[5, 5]`` float32: presence, x, y, vx, vy of the ego and 4 nearest vehicles,
normalised), under ``"observation"``. The sensors read a second type, highway's own
``TimeToCollisionObservation`` (``compute_ttc_grid``: for each ego speed (slower, current,
faster), lane (left, current, right) and 1 s time bin, whether a vehicle would be reached then),
built on the same unwrapped env inside the declared ``sensors`` function, so the env keeps one
observation type and nothing is simulated twice. Lanes off the road read as occupied (highway's
own padding).

**Binary sensors** (``SENSOR_NAMES``, ``K = 6``), at the current ego speed: for each lane (left,
current, right), a vehicle within ``NEAR_S`` = 1 s and within ``FAR_S`` = 3 s (time bins below
the horizon; highway quantises the time to collision to whole seconds up and down, so "within
1 s" is bin 0 or 1, i.e. a predicted collision in under 2 s).

**Collision**: ``info["crashed"]``, charged to the chosen action. **Rewards**: highway's reward
is normalised, ``(0.1 right_lane + 0.4 high_speed - 1 crashed + 1) / 1.5``, times ``on_road``;
a crash takes ``1 / 1.5`` off it. So the declared ``penalty`` is ``2/3`` and the declared
``task_reward`` (highway's reward plus the penalty on a crash) is highway's reward without its
collision term; the conventional reward (task + collision vector) is highway's own (on a crash
to rounding: ``(r + 2/3) - 2/3``). It is declared, not the adapter's default: a crash still earns
highway's normalised reward ``>= 0``, where the default needs an env reward of at most
``-penalty`` on a collision, so that it never pays for one.

**The oracle** (``ORACLE``, what we believe before any data): a lane change is decided by the
lane it moves to (LANE_LEFT by the left lane, LANE_RIGHT by the right lane, near and far), and
IDLE, FASTER and SLOWER by the current lane ahead (near and far for IDLE and FASTER, near only
for SLOWER: slowing down can still hit a vehicle already within a second).
``tests/test_highway.py`` and the experiment's ``factor-q-learned`` method let the structure
learner say whether it agrees.
"""

from __future__ import annotations

from dataclasses import replace
from types import ModuleType
from typing import Any

import numpy as np

from factorq_envs.gymnasium_adapter import (
    Declaration,
    FactorQEnv,
    Transition,
    make_registered,
    require_extra,
)

#: The optional extra that installs highway-env.
EXTRA = "factorq-torch[highway]"
ENV_ID = "highway-fast-v0"
ACTUATOR_NAMES = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
#: The time-to-collision horizons of the sensors, in seconds (1 s bins at policy_frequency 1).
NEAR_S, FAR_S = 1, 3
#: The TTC observation's horizon: the farthest sensor's bins and the one past it.
HORIZON_S = FAR_S + 1
LANES = ("left", "front", "right")
SENSOR_NAMES = tuple(f"{lane}<{h}s" for lane in LANES for h in (NEAR_S, FAR_S))
#: The crash's share of highway's normalised reward (collision_reward -1 over the range 1.5).
PENALTY = 1.0 / 1.5


def _oracle(paired: bool = False) -> tuple[tuple[bool, ...], ...]:
    near, far = NEAR_S, FAR_S
    parents = {
        "LANE_LEFT": (f"left<{near}s", f"left<{far}s"),
        "IDLE": (f"front<{near}s", f"front<{far}s"),
        "LANE_RIGHT": (f"right<{near}s", f"right<{far}s"),
        "FASTER": (f"front<{near}s", f"front<{far}s"),
        "SLOWER": (f"front<{near}s",),
    }
    if paired:  # what the data support (docs/decisions.md, "highway-env's sensors ...")
        parents.update(
            LANE_LEFT=(f"left<{near}s", f"front<{near}s"),
            IDLE=(f"front<{near}s",),
            LANE_RIGHT=(f"right<{near}s", f"front<{near}s"),
            FASTER=(f"front<{near}s",),
        )
    return tuple(tuple(name in parents[a] for name in SENSOR_NAMES) for a in ACTUATOR_NAMES)


#: What we believe decides each action's crash, ``[5, 6]`` (module docstring).
ORACLE = _oracle()
#: What the data support: a lane change's crash decided by its target lane and the vehicle
#: ahead together, IDLE and FASTER by the vehicle ahead within 1 s (the ``highway-pairs`` world).
PAIRED_ORACLE = _oracle(paired=True)


def require_highway() -> ModuleType:
    """Import ``highway_env`` (registering its envs), or one ModuleNotFoundError naming the
    extra."""
    return require_extra("highway_env", EXTRA)


def ttc_sensors(step: Transition) -> np.ndarray:
    """``[6]`` bool from highway's ``TimeToCollisionObservation`` of the env (module docstring)."""
    from highway_env.envs.common.observation import TimeToCollisionObservation

    grid = TimeToCollisionObservation(step.env.unwrapped, horizon=HORIZON_S).observe()  # [3, 3, T]
    current = grid[1]  # the current ego speed: [lanes (left, current, right), time bins]
    # a collision predicted in time bin t (t s up or down): within h s is bins 0..h
    near = (current[:, : NEAR_S + 1] > 0).any(axis=1)
    far = (current[:, : FAR_S + 1] > 0).any(axis=1)
    return np.stack([near, far], axis=1).reshape(-1)  # left<1, left<3, front<1, ...


def task_reward(step: Transition) -> float:
    """highway's reward without its crash term: its reward plus ``PENALTY`` on a crash (a crash
    still earns highway's normalised reward ``>= 0``, so the adapter's default, which needs an
    env reward of at most ``-penalty`` on a collision, cannot see the penalty in it)."""
    return step.reward + PENALTY if step.info["crashed"] else step.reward


DECLARATION = Declaration(
    num_sensors=len(SENSOR_NAMES),
    sensors=ttc_sensors,
    collision="crashed",
    task_reward=task_reward,
    actuator_names=ACTUATOR_NAMES,
    dependency=ORACLE,
    sensor_names=SENSOR_NAMES,
    penalty=PENALTY,
)


def make_highway(
    seed: int | None = None, env_id: str = ENV_ID, paired: bool = False, **config: Any
) -> FactorQEnv:
    """The adapter around highway-env's ``env_id`` (default ``highway-fast-v0``; ``config``
    entries update highway's own config); ``seed``: its first reset's seed; ``paired``: declare
    ``PAIRED_ORACLE`` instead of ``ORACLE``."""
    require_highway()
    env = make_registered(env_id, config=config or None, disable_env_checker=True)
    declaration = replace(DECLARATION, dependency=PAIRED_ORACLE) if paired else DECLARATION
    return FactorQEnv(env, declaration, seed=seed)
