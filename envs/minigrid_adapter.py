"""MiniGrid's Dynamic-Obstacles worlds as Factor-Q sees them: a declaration on the Gymnasium
adapter (``factorq_envs.gymnasium_adapter``; issues 16 and 25), not a copy.

MiniGrid (Farama, ``minigrid`` 3.2.0, the optional extra ``factorq-torch[minigrid]``) is stepped
as it is; this file only *declares* how Factor-Q reads it. ``MiniGrid-Dynamic-Obstacles-{5x5,
6x6,8x8,16x16}-v0``: an empty room, the goal in the bottom-right corner, balls that random-walk in
their 3x3 neighbourhood every step; actions turn left, turn right, forward; forward into a wall
or ball gives -1 and ends the episode, decided on the grid *before* the balls move; the goal
gives ``1 - 0.9 t / max_steps`` (``max_steps = 4 size**2``).

**The body** is ``factorq_envs.body.HEADING`` (forward, turn-left, turn-right: Factor-Q's action
``a`` is MiniGrid's ``ACTION_TO_MINIGRID[a]``, the declaration's ``actions``). **The heading** is
MiniGrid's ``direction`` (0 east, 1 south, 2 west, 3 north; left turn subtracts 1) in the
project's numbering (0 north, 1 west, 2 south, 3 east; left turn adds 1): ``heading = (3 -
direction) % 4``. **The cell** is ``y * width + x`` of MiniGrid's ``agent_pos`` (walls included:
``size**2`` cells). Together they are the declaration's ``task_state``.

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
collision, charged to the chosen actuator, which is always forward (the only actuator that
moves): ``collision`` ``[A]`` is -1 at forward, 0 elsewhere, and ``bump`` marks it. The task
reward is the declaration's default (MiniGrid's reward without the collision: the goal reward, 0
on a collision step), so ``SplitLocalReward`` gives the task reward and the local reward vector as
for ``FactoredGridEnv``. ``tests/test_minigrid.py`` checks that the collision equals "front cell
(read from the unwrapped env before the step) is wall or ball, and the action is forward" on
every step.

**Collision semantics** (``SEMANTICS``): ``"minigrid"``, MiniGrid's own (a collision ends the
episode); ``"nodeath"``, ``minigrid.wrappers.NoDeath(env, ("ball", "wall"), 0.0)``: the episode
goes on after a collision (still -1), like the paper's world; it then ends at the goal or by
truncation at ``max_steps``. (MiniGrid checks the front cell before the balls move, then moves
them, then the agent: if the ball in front moved away, forward still counts as a collision and the
agent does move; under ``"nodeath"`` it goes on from its new cell.)

Two ways in:

- ``make_minigrid(size)``: a ``FactorQEnv`` (a ``gymnasium.Wrapper``) whose observation is
  MiniGrid's own (``image``, ``direction``, ``mission`` as a plain ``Text``) plus ``cell``,
  ``heading``, ``sensors``, ``bump``, ``collision``: Gymnasium's ``check_env``, MiniGrid's
  ``ImgObsWrapper`` and ``FlatObsWrapper``, ``gymnasium.vector`` envs and torchrl's
  ``GymWrapper`` / ``SerialEnv`` / ``ParallelEnv`` take it.
- ``MiniGridEnv`` (``factorq_envs.minigrid_torchrl``, loaded on first use, so this file needs no
  torchrl): ``S`` of them as one torchrl env of ``batch_size=(S,)`` (the adapter's
  ``declared_torchrl_env``), with the project's keys and dtypes, for the online collector and
  DQN. The compiled kernel (``trainers/fast.py``) cannot step MiniGrid: the tabular agents run on
  the modular torchrl path.
"""

from __future__ import annotations

import importlib
import string
from collections.abc import Callable
from types import ModuleType
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from factorq_envs.body import HEADING, NUM_HEADINGS, SensorLayout, base_dependency
from factorq_envs.gymnasium_adapter import Declaration, FactorQEnv, Transition, require_extra

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
#: MiniGrid's mission as a plain Gymnasium ``Text`` (torchrl reads ``Text``, not MiniGrid's own
#: ``MissionSpace``; ``FlatObsWrapper`` reads the string itself).
MISSION_SPACE = gym.spaces.Text(max_length=96, charset=string.printable)

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


def require_minigrid() -> ModuleType:
    """Import ``minigrid`` (registering its envs), or raise one ModuleNotFoundError naming the
    extra to install."""
    return require_extra("minigrid", EXTRA)


def env_id(size: int) -> str:
    """The gymnasium id of the Dynamic-Obstacles world of side ``size``."""
    if size not in SIZES:
        sizes = ", ".join(map(str, SIZES))
        raise ValueError(f"size={size!r} is not a Dynamic-Obstacles size: choose one of {sizes}")
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


def _blocked_cells(cells: np.ndarray, step: Transition) -> np.ndarray:
    """The view cells ``cells`` ``[K, 2]`` that hold a wall or a ball, ``[K]`` bool."""
    kinds = step.observation["image"][cells[:, 0], cells[:, 1], 0]
    return (kinds == BLOCKING["wall"]) | (kinds == BLOCKING["ball"])


def _cell_and_heading(size: int, step: Transition) -> tuple[int, int]:
    minigrid: Any = step.env.unwrapped
    x, y = minigrid.agent_pos
    return int(y) * size + int(x), minigrid_heading(int(step.observation["direction"]))


def _collided(step: Transition) -> bool:
    return step.reward < 0  # only a collision gives MiniGrid a negative reward


def declaration(size: int, layout: str = "front3") -> Declaration:
    """What Factor-Q reads from MiniGrid's Dynamic-Obstacles world of side ``size`` (module
    docstring): the whole adapter, as data."""
    chosen = check_layout(layout)
    return Declaration(
        num_sensors=chosen.num_sensors,
        sensors=partial_of(_blocked_cells, np.array(view_cells(chosen))),
        collision=_collided,
        actions=ACTION_TO_MINIGRID,
        actuator_names=HEADING.actuators,
        task_state=partial_of(_cell_and_heading, size),
        num_cells=size * size,
        num_headings=HEADING.num_headings,
        dependency=tuple(map(tuple, dependency(layout).tolist())),
        sensor_names=chosen.names(HEADING),
        spaces={"mission": MISSION_SPACE},
    )


def partial_of(function: Callable[..., Any], *args: Any) -> Callable[..., Any]:
    """``functools.partial`` (picklable, so the declaration travels to worker processes)."""
    from functools import partial

    return partial(function, *args)


def make_minigrid(
    size: int,
    semantics: str = "minigrid",
    *,
    layout: str = "front3",
    seed: int | None = None,
    render_mode: str | None = None,
) -> FactorQEnv:
    """The adapter around MiniGrid's own ``MiniGrid-Dynamic-Obstacles-{size}x{size}-v0``
    (``semantics="nodeath"``: inside ``NoDeath(env, ("ball", "wall"), 0.0)``); ``seed``: the seed
    of its first reset that is given none."""
    require_minigrid()
    from minigrid.wrappers import NoDeath

    check_semantics(semantics)
    check_layout(layout)
    env = gym.make(env_id(size), render_mode=render_mode, disable_env_checker=True)
    if semantics == "nodeath":
        env = NoDeath(env, ("ball", "wall"), 0.0)
    return FactorQEnv(env, declaration(size, layout), seed=seed)


def __getattr__(name: str) -> Any:
    if name == "MiniGridEnv":
        return importlib.import_module("factorq_envs.minigrid_torchrl").MiniGridEnv
    raise AttributeError(f"module 'factorq_envs.minigrid_adapter' has no attribute {name!r}")
