"""MiniGrid's Dynamic-Obstacles worlds as Factor-Q sees them: an adapter, not a copy (issue 16).

MiniGrid (Farama, ``minigrid`` 3.2.0, the optional extra ``factorq-torch[minigrid]``) is stepped
as it is; this file only *reads* it. ``MiniGrid-Dynamic-Obstacles-{5x5,6x6,8x8,16x16}-v0``: an
empty room, the goal in the bottom-right corner, balls that random-walk in their 3x3
neighbourhood every step; actions turn left, turn right, forward; forward into a wall or ball
gives -1 and ends the episode, decided on the grid *before* the balls move; the goal gives
``1 - 0.9 t / max_steps`` (``max_steps = 4 size**2``).

**The body** is ``factorq_envs.body.HEADING`` (forward, turn-left, turn-right: Factor-Q's action
``a`` is MiniGrid's ``ACTION_TO_MINIGRID[a]``). **The heading** is MiniGrid's ``agent_dir`` (0 east,
1 south, 2 west, 3 north; left turn subtracts 1) in the project's numbering (0 north, 1 west, 2
south, 3 east; left turn adds 1): ``heading = (3 - agent_dir) % 4``. **The cell** is ``y *
width + x`` of MiniGrid's ``agent_pos`` (walls included: ``size**2`` cells).

**The sensors** are cells of MiniGrid's own egocentric 7x7 view (``obs["image"]``, indexed
``[x, y]``, the agent at ``(3, 6)`` facing up): sensor ``k`` is 1 when that view cell holds a wall
(object index 2) or a ball (6). The layouts (``VIEW_LAYOUTS``) are
``factorq_envs.body.SensorLayout`` entries, offsets ``(d_row, d_col)`` in the frame of heading 0
(ahead is ``-1`` rows), so the view cell of an offset is ``(3 + d_col, 6 + d_row)``:

- ``"front3"`` (default): front ``image[3, 5]``, left ``image[2, 6]``, right ``image[4, 6]``;
- ``"ahead6"``: those, then front-left ``image[2, 5]``, front-right ``image[4, 5]`` and the cell
  two ahead, front-front ``image[3, 4]`` (more cells the learner must rule out; the balls there
  may move into the front cell this step).

MiniGrid cannot see behind the agent, so no layout has a "back" sensor.

**Rewards.** The conventional ``reward`` is MiniGrid's own. A collision is read from MiniGrid's
outcome, not recomputed: a negative MiniGrid reward (only a collision gives one) is the
collision, attributed to forward (the only actuator that moves): ``collision`` ``[A]`` is -1 at
forward, 0 elsewhere, and ``bump`` marks it. So, as for ``FactoredGridEnv``, ``SplitLocalReward``
gives the task reward (the goal reward; 0 on a collision step) and the local reward vector.
``tests/test_minigrid.py`` checks that the collision equals "front cell (read from the unwrapped
env before the step) is wall or ball, and the action is forward" on every step.

**Collision semantics** (``SEMANTICS``): ``"minigrid"``, MiniGrid's own (a collision ends the
episode); ``"nodeath"``, ``minigrid.wrappers.NoDeath(env, ("ball", "wall"), 0.0)``: the episode
goes on after a collision (still -1), like the paper's world; it then ends at the goal or by
truncation at ``max_steps``. (MiniGrid checks the front cell before the balls move, then moves
them, then the agent: if the ball in front moved away, forward still counts as a collision and the
agent does move; under ``"nodeath"`` it goes on from its new cell.)

Two ways in:

- ``FactoredMiniGrid``: a ``gymnasium.Wrapper`` with a ``Dict`` observation (``cell``,
  ``heading``, ``sensors``, ``bump``, ``collision`` and, with ``with_image``, MiniGrid's
  ``image``), no ``mission`` string (torchrl's ``GymWrapper`` refuses text spaces): usable with
  ``gymnasium.vector`` envs and with torchrl's ``GymWrapper`` / ``SerialEnv`` / ``ParallelEnv``.
- ``MiniGridEnv`` (``factorq_envs.minigrid_env``, loaded on first use, so this file needs no
  torchrl): a torchrl ``EnvBase`` of ``batch_size=(S,)`` holding ``S`` of them (one seed
  each) with the project's keys and dtypes (``sensors``/``bump`` bool, as ``FactoredGridEnv``), for
  the online collector and DQN. The compiled kernel (``trainers/fast.py``) cannot step MiniGrid:
  the tabular agents run on the modular torchrl path.
"""

from __future__ import annotations

import importlib
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from factorq_envs.body import HEADING, NUM_HEADINGS, SensorLayout, base_dependency
from factorq_torch.base import keys

#: The optional extra that installs MiniGrid.
EXTRA = "factorq-torch[minigrid]"
#: The Dynamic-Obstacles sizes registered by MiniGrid 3.2.0 (with a fixed start).
SIZES = (5, 6, 8, 16)
SEMANTICS = ("minigrid", "nodeath")
#: MiniGrid's object indices that block the agent (``minigrid.core.constants.OBJECT_TO_IDX``).
BLOCKING = {"wall": 2, "ball": 6}
#: Factor-Q's actuators (``HEADING.actuators``) as MiniGrid's actions (0 left, 1 right, 2 forward).
_MINIGRID_ACTION = {"forward": 2, "turn-left": 0, "turn-right": 1}
ACTION_TO_MINIGRID = tuple(_MINIGRID_ACTION[name] for name in HEADING.actuators)
#: The actuator that moves (and so the only one that can collide).
FORWARD = HEADING.moves.index(0)
VIEW_SIZE = 7
#: The agent's cell in the egocentric view, ``(x, y)``.
AGENT_VIEW = (VIEW_SIZE // 2, VIEW_SIZE - 1)

_FRONT3 = ((-1, 0), (0, -1), (0, 1))
VIEW_LAYOUTS = {
    "front3": SensorLayout(name="front3", offsets=_FRONT3, directions=((0,), (1,), (3,))),
    "ahead6": SensorLayout(
        name="ahead6",
        offsets=(*_FRONT3, (-1, -1), (-1, 1), (-2, 0)),
        directions=((0,), (1,), (3,), (0, 1), (0, 3), (0, 0)),
    ),
}


def minigrid_heading(agent_dir: int) -> int:
    """MiniGrid's ``agent_dir`` (0 east, a left turn subtracts 1) as the project's heading (0
    north, a left turn adds 1): east is our last direction, so ``(H - 1 - agent_dir) mod H``."""
    return (NUM_HEADINGS - 1 - agent_dir) % NUM_HEADINGS


def require_minigrid():
    """Import ``minigrid`` (registering its envs), or raise one ModuleNotFoundError naming the
    extra to install."""
    try:
        return importlib.import_module("minigrid")
    except ModuleNotFoundError as error:
        if error.name is not None and error.name.split(".")[0] != "minigrid":
            raise
        raise ModuleNotFoundError(
            f"MiniGrid is not installed: install the optional extra with pip install '{EXTRA}'",
            name="minigrid",
        ) from None


def env_id(size: int) -> str:
    """The gymnasium id of the Dynamic-Obstacles world of side ``size``."""
    if size not in SIZES:
        raise ValueError(f"size={size!r} is not a Dynamic-Obstacles size: choose one of {SIZES}")
    return f"MiniGrid-Dynamic-Obstacles-{size}x{size}-v0"


def check_semantics(semantics: str) -> str:
    if semantics not in SEMANTICS:
        raise ValueError(
            f"semantics={semantics!r} is unknown: choose one of {', '.join(SEMANTICS)} (MiniGrid's "
            f"own: a collision ends the episode; nodeath: it goes on, like the paper)"
        )
    return semantics


def check_layout(layout: str) -> SensorLayout:
    if layout not in VIEW_LAYOUTS:
        raise ValueError(f"layout={layout!r} is unknown: choose one of {', '.join(VIEW_LAYOUTS)}")
    return VIEW_LAYOUTS[layout]


def view_cells(layout: SensorLayout) -> tuple[tuple[int, int], ...]:
    """The ``(x, y)`` cell of MiniGrid's view each sensor of ``layout`` reads."""
    return tuple((AGENT_VIEW[0] + d_col, AGENT_VIEW[1] + d_row) for d_row, d_col in layout.offsets)


def dependency(layout: str = "front3") -> torch.Tensor:
    """Bool ``[3, K]``: forward's collision is decided by the front sensor; the turns by none."""
    return base_dependency(HEADING, check_layout(layout), 0)


def sensor_names(layout: str = "front3") -> tuple[str, ...]:
    return check_layout(layout).names(HEADING)


class FactoredMiniGrid(gym.Wrapper):
    """A MiniGrid env with Factor-Q's observation and action numbering (module docstring).

    Args:
        env: a MiniGrid Dynamic-Obstacles env (``gymnasium.make(env_id(size))``, possibly
            wrapped in ``NoDeath``).
        layout: the sensors, a key of ``VIEW_LAYOUTS``.
        with_image: also return MiniGrid's 7x7x3 ``image`` (for the image-based DQN).

    Observation (``Dict``): ``cell`` int, ``heading`` int, ``sensors`` ``MultiBinary(K)``,
    ``bump`` ``MultiBinary(A)``, ``collision`` ``Box(-1, 0, (A,))``, [``image``]. Actions:
    ``Discrete(3)``, 0 forward, 1 turn-left, 2 turn-right. Reward: MiniGrid's. ``info`` adds
    ``collided`` and ``success`` (the goal was reached).
    """

    def __init__(self, env, layout: str = "front3", with_image: bool = False) -> None:
        super().__init__(env)
        base = env.unwrapped
        if not hasattr(base, "agent_dir") or not hasattr(base, "agent_view_size"):
            raise TypeError(f"env must be a MiniGrid env, got {type(base).__name__}")
        if base.agent_view_size != VIEW_SIZE:
            raise ValueError(f"agent_view_size={base.agent_view_size}: the layouts need 7")
        self.layout = check_layout(layout)
        self.with_image = bool(with_image)
        self._cells = np.array(view_cells(self.layout))  # [K, 2]
        self.num_sensors = self.layout.num_sensors
        self.num_actions = HEADING.num_actuators
        self.num_cells = base.width * base.height
        spaces = {
            keys.CELL: gym.spaces.Discrete(self.num_cells),
            keys.HEADING: gym.spaces.Discrete(HEADING.num_headings),
            keys.SENSORS: gym.spaces.MultiBinary(self.num_sensors),
            keys.BUMP: gym.spaces.MultiBinary(self.num_actions),
            keys.COLLISION: gym.spaces.Box(-1.0, 0.0, (self.num_actions,), np.float32),
        }
        if self.with_image:
            spaces["image"] = base.observation_space["image"]
        self.observation_space = gym.spaces.Dict(spaces)
        self.action_space = gym.spaces.Discrete(self.num_actions)

    def _observe(self, obs: dict[str, Any], collided: bool) -> dict[str, Any]:
        base: Any = self.env.unwrapped  # a MiniGridEnv (checked in __init__), untyped
        image = obs["image"]
        kinds = image[self._cells[:, 0], self._cells[:, 1], 0]
        sensors = ((kinds == BLOCKING["wall"]) | (kinds == BLOCKING["ball"])).astype(np.int8)
        bump = np.zeros(self.num_actions, dtype=np.int8)
        collision = np.zeros(self.num_actions, dtype=np.float32)
        if collided:
            bump[FORWARD] = 1
            collision[FORWARD] = -1.0
        x, y = base.agent_pos
        out = {
            keys.CELL: int(y) * base.width + int(x),
            keys.HEADING: minigrid_heading(int(base.agent_dir)),
            keys.SENSORS: sensors,
            keys.BUMP: bump,
            keys.COLLISION: collision,
        }
        if self.with_image:
            out["image"] = image
        return out

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._observe(obs, False), dict(info, collided=False, success=False)

    def step(self, action):
        action = int(action)
        if not 0 <= action < self.num_actions:
            raise ValueError(
                f"action={action} is out of range: must be in [0, {self.num_actions - 1}] "
                f"({', '.join(HEADING.actuators)})"
            )
        obs, reward, terminated, truncated, info = self.env.step(ACTION_TO_MINIGRID[action])
        collided = reward < 0  # only a collision gives MiniGrid a negative reward
        info = dict(info, collided=collided, success=bool(reward > 0))
        return self._observe(obs, collided), float(reward), terminated, truncated, info


def make_minigrid(
    size: int,
    semantics: str = "minigrid",
    *,
    layout: str = "front3",
    with_image: bool = False,
    render_mode: str | None = None,
) -> FactoredMiniGrid:
    """``FactoredMiniGrid`` around MiniGrid's own ``MiniGrid-Dynamic-Obstacles-{size}x{size}-v0``
    (``semantics="nodeath"``: inside ``NoDeath(env, ("ball", "wall"), 0.0)``)."""
    require_minigrid()
    from minigrid.wrappers import NoDeath

    check_semantics(semantics)
    check_layout(layout)
    env = gym.make(env_id(size), render_mode=render_mode, disable_env_checker=True)
    if semantics == "nodeath":
        env = NoDeath(env, ("ball", "wall"), 0.0)
    return FactoredMiniGrid(env, layout=layout, with_image=with_image)


def __getattr__(name: str):
    if name == "MiniGridEnv":
        return importlib.import_module("factorq_envs.minigrid_env").MiniGridEnv
    raise AttributeError(f"module 'factorq_envs.minigrid' has no attribute {name!r}")
