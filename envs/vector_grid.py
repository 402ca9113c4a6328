"""A grid body with simultaneous actuators: two drives that fire together (issue 40, item 4).

The paper's agent fires exactly one of four actuators per step; its conclusion names "multiple
independent simultaneous actions, necessitating the use of an action vector", where "correct
reward assignment is made much easier if the various rewards arising from the actions are kept
separate". This world is that body on the paper's grid:

- the **action is a vector** of two actuators, each with three values: a horizontal drive
  (index 0: west, 1: still, 2: east) and a vertical drive (index 0: north, 1: still, 2: south),
  ``MultiDiscrete([3, 3])`` in Gymnasium, nine joint actions (diagonal moves and standing still
  among them);
- the sensors are the paper's four proximity bits (north, west, south, east);
- **each drive has its own local reward**: ``collision[j] = -1`` when drive ``j`` pushed into a
  wall or an obstacle on its own face (the neighbour in its direction, from the cell the step
  started in), 0 otherwise: a vector of two, never summed (``drive_collisions``). A blocked
  component does not move; the other one still does;
- a diagonal move whose two faces are free but whose diagonal cell holds an obstacle slides
  along its horizontal component (no bump: neither face was blocked), so every collision is
  decided by the one sensor of its drive's direction (``drive_dependency``), as in the paper;
- rewards otherwise as SPEC section 2: -1 per step, +1 on reaching the goal, conventional reward
  ``task + sum(collision)``; start top-left, goal bottom-right; obstacles static (drawn once
  from ``layout_seed``, redrawn until the goal is reachable) or scattered again every
  ``obstacle_period`` steps, with the grid's own functions (``factorq_envs.grid_functions``).

The pure batched functions (``initial_vector_state``, ``reset_vector_worlds``,
``step_vector_worlds``) run ``S`` independent worlds; ``VectorGridGym`` is one of them for
Gymnasium and ``factorq_envs.vector_torchrl.VectorGridEnv`` a batch for torchrl.

Example (a 3x3 grid, no obstacles; the agent starts top-left):

    >>> env = VectorGridGym(size=3, num_obstacles=0)
    >>> observation, info = env.reset(seed=0)
    >>> observation["sensors"].tolist()  # north and west are walls
    [1, 1, 0, 0]
    >>> observation, reward, terminated, truncated, info = env.step([0, 2])  # west and south
    >>> info["local_reward"].tolist(), float(info["task_reward"]), reward  # only west bumped
    ([-1.0, 0.0], -1.0, -2.0)
    >>> int(observation["cell"])  # the vertical drive still moved: one row down
    3
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import gymnasium
import numpy as np
import torch
from gymnasium import spaces

from factorq_envs.grid_config import WorldConfig
from factorq_envs.grid_functions import (
    START_CELL,
    proximity,
    scatter_obstacles,
    shortest_path_length,
    static_layout,
)
from factorq_envs.gym_spaces import FlagSpace, IndexSpace, register_if_torchrl_loaded
from factorq_torch.base.rng import STREAM_WORLD, derive_keys
from factorq_torch.base.validation import check_int

#: The actuators (drives), in the order of the action vector.
DRIVES = ("horizontal", "vertical")
#: What each value index of a drive does: -1 (west / north), 0 (still), +1 (east / south).
DRIVE_VALUES = (-1, 0, 1)
#: The values each drive takes (``MultiDiscrete`` ``nvec``).
NVEC = (len(DRIVE_VALUES), len(DRIVE_VALUES))
#: The sensors, as the paper's: the neighbour in each direction is blocked.
SENSOR_NAMES = ("north", "west", "south", "east")
#: The sensor (a paper direction: 0 north, 1 west, 2 south, 3 east) each drive value pushes
#: against, or None for "still".
DRIVE_DIRECTIONS = ((1, None, 3), (0, None, 2))


def drive_dependency() -> torch.Tensor:
    """Which sensor decides each actuator value's collision: bool ``[sum(NVEC), 4]``, rows in
    the order (horizontal west, still, east, vertical north, still, south).

    >>> drive_dependency().int().tolist()
    [[0, 1, 0, 0], [0, 0, 0, 0], [0, 0, 0, 1], [1, 0, 0, 0], [0, 0, 0, 0], [0, 0, 1, 0]]
    """
    rows = [
        [direction == sensor for sensor in range(len(SENSOR_NAMES))]
        for directions in DRIVE_DIRECTIONS
        for direction in directions
    ]
    return torch.tensor(rows, dtype=torch.bool)


def check_action_vector(action: Any, nvec: Sequence[int], where: str) -> np.ndarray:
    """``action`` as an int64 array ``[len(nvec)]`` with entry ``j`` in ``[0, nvec[j])``, else
    one error naming both lengths (or the entry out of range) and ``where``."""
    array = np.asarray(action)
    if array.dtype.kind not in "iu" or array.ndim != 1:
        raise TypeError(
            f"{where}: the action must be a vector of {len(nvec)} integers (one per actuator), "
            f"got {action!r}"
        )
    if array.shape[0] != len(nvec):
        raise ValueError(
            f"{where}: the action vector has length {array.shape[0]} but the body has "
            f"{len(nvec)} actuators (nvec={list(nvec)})"
        )
    bad = [j for j, (a, n) in enumerate(zip(array.tolist(), nvec, strict=True)) if not 0 <= a < n]
    if bad:
        raise ValueError(
            f"{where}: action {array.tolist()} is out of range at actuators {bad}: entry j must "
            f"be in [0, nvec[j]) with nvec={list(nvec)}"
        )
    return array.astype(np.int64)


@dataclass(frozen=True)
class VectorGridConfig:
    """The parameters of the two-drive world (module docstring).

    Args:
        size: the grid is ``size`` x ``size`` cells.
        num_obstacles: single-cell obstacles, never on the start, the goal or the agent.
        obstacle_period: 0 static (one layout from ``layout_seed``), ``k > 0``: scattered at
            every reset and after every ``k``-th step (10 semi-dynamic, 1 dynamic).
        max_steps: an episode is truncated after this many steps.
        layout_seed: the static layout's seed.
    """

    size: int = 10
    num_obstacles: int = 10
    obstacle_period: int = 0
    max_steps: int = 10_000
    layout_seed: int = 0

    def __post_init__(self) -> None:
        check_int("size", self.size, 2)
        check_int("num_obstacles", self.num_obstacles, 0, self.size * self.size - 3)
        check_int("obstacle_period", self.obstacle_period, 0)
        check_int("max_steps", self.max_steps, 1)
        check_int("layout_seed", self.layout_seed, 0)

    @property
    def num_cells(self) -> int:
        return self.size * self.size

    @property
    def goal_cell(self) -> int:
        return self.num_cells - 1

    @property
    def num_sensors(self) -> int:
        return len(SENSOR_NAMES)

    @property
    def num_actuators(self) -> int:
        return len(DRIVES)

    @property
    def num_headings(self) -> int:
        return 1

    @property
    def nvec(self) -> tuple[int, ...]:
        return NVEC

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return DRIVES


class VectorState(NamedTuple):
    """``S`` worlds of the two-drive body (every tensor has the leading dimension ``S``)."""

    cell: torch.Tensor  # [S] int64
    obstacles: torch.Tensor  # [S, N] bool
    bump: torch.Tensor  # [S, 2] bool, the drives that bumped on the last step
    episode_step: torch.Tensor  # [S] int64
    scatters: torch.Tensor  # [S] int64, scatters drawn so far (the stream's position)


class VectorOutcome(NamedTuple):
    """What one step of ``S`` worlds produced."""

    step_reward: torch.Tensor  # [S] float32, -1
    goal_reward: torch.Tensor  # [S] float32, +1 on reaching the goal
    collision: torch.Tensor  # [S, 2] float32, -1 on each drive that bumped
    terminated: torch.Tensor  # [S] bool
    truncated: torch.Tensor  # [S] bool

    @property
    def task_reward(self) -> torch.Tensor:
        """step + goal: what Factor-Q's task table learns from."""
        return self.step_reward + self.goal_reward

    @property
    def reward(self) -> torch.Tensor:
        """The conventional scalar reward, step + goal + sum(collision) (flat Q-learning)."""
        return self.task_reward + self.collision.sum(dim=-1)


def drive_collisions(sensors: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """The per-actuator assignment: drive ``j`` bumps when it pushes toward a blocked face.

    Shapes: ``sensors [..., 4]`` bool (north, west, south, east), ``action [..., 2]`` int64 value
    indices -> ``[..., 2]`` bool. "Still" (index 1) never bumps.

    >>> sensors = torch.tensor([[True, True, False, False]])  # north and west blocked
    >>> drive_collisions(sensors, torch.tensor([[0, 0]])).tolist()  # west and north: both bump
    [[True, True]]
    >>> drive_collisions(sensors, torch.tensor([[2, 0]])).tolist()  # east free, north bumps
    [[False, True]]
    """
    # the sensor each (drive, value) pushes against; "still" reads a column of False
    padded = torch.cat([sensors, torch.zeros_like(sensors[..., :1])], dim=-1)  # [..., 5]
    still = padded.shape[-1] - 1
    table = torch.tensor(
        [[still if d is None else d for d in directions] for directions in DRIVE_DIRECTIONS],
        device=action.device,
    )  # [2, 3]
    faced = table.gather(1, action.reshape(-1, 2).T).T.reshape(action.shape)  # [..., 2]
    return padded.gather(-1, faced)


def initial_vector_state(
    batch: int, config: VectorGridConfig, device: torch.device | str | None = None
) -> VectorState:
    """``batch`` worlds before their first ``reset_vector_worlds``."""
    zeros = torch.zeros(batch, dtype=torch.int64, device=device)
    return VectorState(
        cell=zeros.clone(),
        obstacles=torch.zeros(batch, config.num_cells, dtype=torch.bool, device=device),
        bump=torch.zeros(batch, len(DRIVES), dtype=torch.bool, device=device),
        episode_step=zeros.clone(),
        scatters=zeros.clone(),
    )


def vector_layout(config: VectorGridConfig) -> torch.Tensor:
    """The static layout ``[N]`` bool: the grid's own (``static_layout``), so a layout seed
    draws the same obstacles as the paper's world of that size."""
    return static_layout(
        WorldConfig(
            size=config.size, num_obstacles=config.num_obstacles, layout_seed=config.layout_seed
        )
    )


def reset_vector_worlds(
    state: VectorState,
    mask: torch.Tensor,
    key: torch.Tensor,
    config: VectorGridConfig,
    layout: torch.Tensor | None = None,
) -> VectorState:
    """New episodes where ``mask`` ``[S]`` is True: the agent on the start, no bump; a static
    world gets ``layout`` (``vector_layout(config)``), a moving one a fresh scatter."""
    obstacles, scatters = state.obstacles, state.scatters
    if config.num_obstacles:
        if config.obstacle_period == 0:
            if layout is None:
                layout = vector_layout(config)
            obstacles = torch.where(mask.unsqueeze(1), layout.to(obstacles.device), obstacles)
        else:
            start = torch.full_like(state.cell, START_CELL)
            fresh = scatter_obstacles(
                key, scatters, start, config.size, config.num_obstacles
            )  # [S, N]
            obstacles = torch.where(mask.unsqueeze(1), fresh, obstacles)
            scatters = scatters + mask
    return VectorState(
        cell=state.cell.masked_fill(mask, START_CELL),
        obstacles=obstacles,
        bump=state.bump.masked_fill(mask.unsqueeze(1), False),
        episode_step=state.episode_step.masked_fill(mask, 0),
        scatters=scatters,
    )


def step_vector_worlds(
    state: VectorState, action: torch.Tensor, key: torch.Tensor, config: VectorGridConfig
) -> tuple[VectorState, VectorOutcome]:
    """Both drives of each of ``S`` worlds fire at once (module docstring).

    ``action`` ``[S, 2]`` int64 value indices. Order: read the action -> each drive bumps or
    moves (``drive_collisions`` on the sensors of the starting cell) -> the unblocked components
    move the agent (a diagonal onto an obstacle keeps only the horizontal one) -> rewards ->
    (maybe) scatter the obstacles. Inputs are not mutated.
    """
    size = config.size
    if action.shape != (*state.cell.shape, len(DRIVES)):
        raise ValueError(
            f"action has shape {tuple(action.shape)}: the two-drive world takes "
            f"[{state.cell.shape[0]}, {len(DRIVES)}] (one value per actuator per world)"
        )
    sensors = proximity(state.cell, state.obstacles, size)  # [S, 4]
    bumped = drive_collisions(sensors, action)  # [S, 2]
    delta = action - 1  # [S, 2], -1 / 0 / +1
    moved = delta.masked_fill(bumped, 0)
    d_col, d_row = moved.unbind(-1)  # [S] each
    cell = state.cell + d_row * size + d_col
    # a diagonal whose corner cell is an obstacle: slide along the horizontal component
    diagonal = (d_row != 0) & (d_col != 0)
    corner = state.obstacles.gather(1, cell.unsqueeze(1)).squeeze(1)
    cell = torch.where(diagonal & corner, state.cell + d_col, cell)
    episode_step = state.episode_step + 1
    terminated = cell == config.goal_cell
    truncated = ~terminated & (episode_step >= config.max_steps)
    outcome = VectorOutcome(
        step_reward=torch.full(cell.shape, -1.0, device=cell.device),
        goal_reward=terminated.to(torch.float32),
        collision=torch.zeros(bumped.shape, device=cell.device).masked_fill_(bumped, -1.0),
        terminated=terminated,
        truncated=truncated,
    )
    obstacles, scatters = state.obstacles, state.scatters
    period = config.obstacle_period
    if config.num_obstacles and period > 0:
        scatter = ~terminated & (episode_step % period == 0)
        fresh = scatter_obstacles(key, scatters, cell, size, config.num_obstacles)
        obstacles = torch.where(scatter.unsqueeze(1), fresh, obstacles)
        scatters = scatters + scatter
    return VectorState(cell, obstacles, bumped, episode_step, scatters), outcome


def vector_shortest_path(obstacles: torch.Tensor, size: int) -> int | None:
    """Steps from start to goal on a shortest path of the two-drive body around ``obstacles``
    ``[N]`` (a breadth-first search over the nine joint actions, with the step's own rules),
    or ``None`` when the goal cannot be reached. An empty 10x10 grid takes 9 diagonal steps.

    >>> vector_shortest_path(torch.zeros(100, dtype=torch.bool), 10)
    9
    """
    if shortest_path_length(obstacles, size) is None:  # no 4-connected path: none at all
        return None
    config = VectorGridConfig(size=size, num_obstacles=0)
    joint = torch.cartesian_prod(torch.arange(3), torch.arange(3))  # [9, 2]
    distance = {START_CELL: 0}
    frontier = [START_CELL]
    while frontier:
        batch = len(frontier)
        state = VectorState(
            cell=torch.tensor(frontier).repeat_interleave(len(joint)),
            obstacles=obstacles.expand(batch * len(joint), -1),
            bump=torch.zeros(batch * len(joint), 2, dtype=torch.bool),
            episode_step=torch.zeros(batch * len(joint), dtype=torch.int64),
            scatters=torch.zeros(batch * len(joint), dtype=torch.int64),
        )
        key = torch.zeros(batch * len(joint), dtype=torch.int64)
        after, _ = step_vector_worlds(state, joint.repeat(batch, 1), key, config)
        reached = []
        for index, cell in enumerate(after.cell.tolist()):
            if cell not in distance:
                distance[cell] = distance[frontier[index // len(joint)]] + 1
                reached.append(cell)
        frontier = reached
    return distance.get(size * size - 1)


def vector_sensors(state: VectorState, config: VectorGridConfig) -> torch.Tensor:
    """The four proximity sensors ``[S, 4]`` bool of each world (north, west, south, east)."""
    return proximity(state.cell, state.obstacles, config.size)


class VectorGridGym(gymnasium.Env):
    """One two-drive world for Gymnasium (module docstring): action ``MultiDiscrete([3, 3])``.

    Args:
        size, num_obstacles, obstacle_period, max_steps, layout_seed: as ``VectorGridConfig``.

    Observation ``Dict(cell=Discrete(N), sensors=MultiBinary(4), bump=MultiBinary(2),
    collision=Box(-1, 0, (2,)))`` (``IndexSpace`` and ``FlagSpace``: torchrl reads an index and
    bools). The reward is the conventional ``task + sum(collision)``; ``info`` holds
    ``"task_reward"`` (float32) and ``"local_reward"`` (float32 ``[2]``, one entry per drive,
    never summed). An action vector of the wrong length is refused, naming both lengths.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        size: int = 10,
        num_obstacles: int = 10,
        obstacle_period: int = 0,
        max_steps: int = 10_000,
        layout_seed: int = 0,
    ) -> None:
        self.config = VectorGridConfig(size, num_obstacles, obstacle_period, max_steps, layout_seed)
        register_if_torchrl_loaded()
        self.observation_space = spaces.Dict(
            {
                "cell": IndexSpace(self.config.num_cells),
                "sensors": FlagSpace(len(SENSOR_NAMES)),
                "bump": FlagSpace(len(DRIVES)),
                "collision": spaces.Box(-1.0, 0.0, (len(DRIVES),), np.float32),
            }
        )
        self.action_space = spaces.MultiDiscrete(list(NVEC))
        self._layout = vector_layout(self.config) if obstacle_period == 0 else None
        self._key = derive_keys(0, STREAM_WORLD, 1)
        self._state = initial_vector_state(1, self.config)
        self._collision = torch.zeros(1, len(DRIVES))

    def _observation(self) -> dict[str, Any]:
        state = self._state
        return {
            "cell": int(state.cell[0]),
            "sensors": vector_sensors(state, self.config)[0].numpy().astype(np.int8),
            "bump": state.bump[0].numpy().astype(np.int8),
            "collision": self._collision[0].numpy().astype(np.float32),
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[str, Any], dict[str, Any]]:
        super().reset(seed=seed)
        if seed is not None:
            self._key = derive_keys(check_int("seed", seed, 0), STREAM_WORLD, 1)
            self._state = initial_vector_state(1, self.config)
        mask = torch.ones(1, dtype=torch.bool)
        self._state = reset_vector_worlds(self._state, mask, self._key, self.config, self._layout)
        self._collision = torch.zeros(1, len(DRIVES))
        return self._observation(), {}

    def step(self, action: Any) -> tuple[dict[str, Any], float, bool, bool, dict[str, Any]]:
        vector = check_action_vector(action, NVEC, "VectorGridGym.step")
        self._state, outcome = step_vector_worlds(
            self._state, torch.from_numpy(vector).unsqueeze(0), self._key, self.config
        )
        self._collision = outcome.collision
        info = {
            "task_reward": np.float32(outcome.task_reward[0]),
            "local_reward": outcome.collision[0].numpy().astype(np.float32),
        }
        return (
            self._observation(),
            float(outcome.reward[0]),
            bool(outcome.terminated[0]),
            bool(outcome.truncated[0]),
            info,
        )
