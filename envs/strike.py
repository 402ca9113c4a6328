"""A world where the task needs the body to strike: the goal room's door opens only when bumped
(the ``factorq_envs.protocol.World`` interface; the paper's section 9).

The paper's grid (``factorq_envs.grid_functions``: its start, moves, sensors, bodies and
collisions) with one fixed layout: the goal sits in a ``room`` x ``room`` room in the bottom-right
corner, walled off by an L of obstacle cells (row ``size - room - 1`` and column
``size - room - 1``), and one cell of that wall is a **door**: the wall cell above the goal's
column, ``(size - room - 1, size - 1)``. The door is an obstacle while closed: the sensors read
it as blocked and a move into it collides (the agent stays, local reward -1 on that actuator)
-- and that collision opens it for the rest of the episode. Every reset closes it again. So
every episode that reaches the goal strikes the door exactly once, and no other path exists.

Rewards: -1 per action, ``goal_reward`` more on the action that reaches the goal (default 100:
the goal is worth a hundred collisions; the paper's grid pays 1), the collision vector as the
local reward. The world is static (``period`` is ignored: nothing scatters).

Plain Factor-Q cannot learn to go through: eqs. 2-3 scale any known local risk above the task's
spread, so a move its local model knows to collide is never its greedy choice, and the door is
struck only by exploration. ``functional.arbitrated_normaliser`` lets the task take priority
when its advantage outweighs any local future (docs/decisions.md, "Arbitration: when the task
takes priority"; ``examples/arbitration.py`` measures it).

>>> from factorq_envs.protocol import World
>>> world = StrikeWorld(StrikeConfig(size=5, room=2))
>>> isinstance(world, World), world.config.door_cell
(True, 14)
>>> key = period = torch.zeros(1, dtype=torch.int64)
>>> state = world.reset(world.initial_state(1), torch.ones(1, dtype=bool), key, period)
>>> print(world.render(state))
#######
#A....#
#.....#
#..ooD#
#..o..#
#..o.G#
#######
>>> state = state._replace(cell=torch.tensor([9]))  # in front of the door
>>> state, outcome = world.step(state, torch.tensor([2]), key, period)  # south: the strike
>>> outcome.collision.tolist(), bool(state.door_open[0]), int(state.cell[0])
([[0.0, 0.0, -1.0, 0.0]], True, 9)
>>> for _ in range(3):  # through the door and down onto the goal
...     state, outcome = world.step(state, torch.tensor([2]), key, period)
>>> bool(outcome.terminated[0]), float(outcome.task_reward[0])
(True, 99.0)
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import torch

from factorq_envs.body import NUM_HEADINGS
from factorq_envs.grid_config import WorldConfig
from factorq_envs.grid_functions import (
    StepOutcome,
    WorldState,
    _move_tables,
    observe,
    proximity,
    render_world,
    reset_worlds,
    step_worlds,
)
from factorq_torch.base.validation import check_float, check_int


@dataclass(frozen=True)
class StrikeConfig:
    """The parameters of the strike world, validated on construction."""

    size: int = 6
    """Side of the square grid, in cells (start top-left, goal bottom-right)."""
    room: int = 2
    """Side of the goal room in the bottom-right corner (the wall around it is one cell thick)."""
    goal_reward: float = 100.0
    """Task reward on reaching the goal, on top of the step's -1 (the paper's grid: 1)."""
    max_steps: int = 1_000
    """Actions after which an episode is truncated."""
    body: str = "translate"
    """The agent's body, as ``WorldConfig.body`` (the paper: translate)."""
    sensors: str = "cross"
    """The sensor layout, as ``WorldConfig.sensors`` (the paper: cross)."""

    def __post_init__(self) -> None:
        check_int("size", self.size, 3)
        check_int("room", self.room, 1, self.size - 2, " (the wall and the start lie outside)")
        check_float("goal_reward", self.goal_reward, -1e6, 1e6)
        check_int("max_steps", self.max_steps, 1)
        _ = self.grid  # WorldConfig validates body and sensors

    @cached_property
    def grid(self) -> WorldConfig:
        """The grid's own config: the body, sensors and rules this world runs (no scattered
        obstacles: the wall and the door are the layout)."""
        return WorldConfig(
            size=self.size,
            num_obstacles=0,
            max_steps=self.max_steps,
            body=self.body,
            sensors=self.sensors,
        )

    @property
    def wall_row(self) -> int:
        """The row (and column) of the room's wall."""
        return self.size - self.room - 1

    @property
    def door_cell(self) -> int:
        """The door: the wall cell above the goal's column."""
        return self.wall_row * self.size + self.size - 1

    @property
    def layout(self) -> torch.Tensor:
        """The obstacles ``[N]`` bool at every reset: the L-shaped wall, the door closed in it."""
        size, wall = self.size, self.wall_row
        cells = torch.zeros(size, size, dtype=torch.bool)
        cells[wall, wall:] = True
        cells[wall:, wall] = True
        return cells.reshape(-1)

    # What the env wrappers read (factorq_envs.protocol.CONFIG_FIELDS): the grid's.
    @property
    def num_cells(self) -> int:
        return self.grid.num_cells

    @property
    def num_sensors(self) -> int:
        return self.grid.num_sensors

    @property
    def num_actuators(self) -> int:
        return self.grid.num_actuators

    @property
    def num_headings(self) -> int:
        return self.grid.num_headings

    @property
    def goal_cell(self) -> int:
        return self.grid.goal_cell

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return self.grid.actuator_names

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return self.grid.sensor_names


class StrikeState(NamedTuple):
    """``S`` strike worlds: the grid's ``WorldState`` fields and whether each door is open."""

    cell: torch.Tensor  # [S] int64
    obstacles: torch.Tensor  # [S, N] bool: the wall, and the door while it is closed
    bump: torch.Tensor  # [S, A] bool
    episode_step: torch.Tensor  # [S] int64
    scatters: torch.Tensor  # [S] int64 (always 0: nothing scatters)
    heading: torch.Tensor  # [S] int64
    ticks: torch.Tensor  # [S] int64
    door_open: torch.Tensor  # [S] bool

    @property
    def grid(self) -> WorldState:
        """The grid's part of the state."""
        return WorldState(*self[:7])


def _with_door(grid: WorldState, door_open: torch.Tensor) -> StrikeState:
    return StrikeState(*grid, door_open=door_open)


class StrikeWorld:
    """``S`` strike worlds as pure batched functions (``factorq_envs.protocol.World``): the grid's
    ``reset_worlds``, ``step_worlds`` and ``observe`` on the fixed layout, plus the door."""

    def __init__(self, config: StrikeConfig | None = None) -> None:
        if config is None:
            config = StrikeConfig()
        if not isinstance(config, StrikeConfig):
            raise TypeError(f"config must be a StrikeConfig, got {type(config).__name__}")
        self.config = config
        self._layout = config.layout

    @property
    def dependency(self) -> torch.Tensor:
        """The grid body's: the door is an obstacle to the sensors like any other."""
        return self.config.grid.dependency

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> StrikeState:
        grid = self.config.grid
        zeros = torch.zeros(batch, dtype=torch.int64, device=device)
        return StrikeState(
            cell=zeros.clone(),
            obstacles=torch.zeros(batch, grid.num_cells, dtype=torch.bool, device=device),
            bump=torch.zeros(batch, grid.num_actuators, dtype=torch.bool, device=device),
            episode_step=zeros.clone(),
            scatters=zeros.clone(),
            heading=zeros.clone(),
            ticks=zeros.clone(),
            door_open=torch.zeros(batch, dtype=torch.bool, device=device),
        )

    def reset(
        self, state: StrikeState, mask: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> StrikeState:
        """New episodes where ``mask``: the agent on the start, the door closed."""
        static = torch.zeros_like(state.cell)  # nothing scatters, whatever the period
        layout = self._layout.to(state.cell.device)
        grid = reset_worlds(state.grid, mask, key, static, layout, self.config.grid)
        return _with_door(grid, state.door_open & ~mask)

    def step(
        self, state: StrikeState, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[StrikeState, StepOutcome]:
        """The grid's step; a collision with the closed door opens it."""
        config = self.config
        grid, outcome = step_worlds(
            state.grid, action, key, torch.zeros_like(state.cell), config.grid
        )
        # the cell the chosen actuator moved towards (as step_worlds computes it)
        move = config.grid._tables["moves"].to(action.device).index_select(0, action)  # [S]
        direction = (move.clamp(min=0) + state.heading) % NUM_HEADINGS
        target_of, _ = _move_tables(config.size, action.device)
        target = target_of.index_select(0, state.cell * NUM_HEADINGS + direction)
        # the door is an obstacle only while closed (then the agent is never on it)
        struck = grid.bump.any(dim=-1) & (move >= 0) & (target == config.door_cell)
        struck = struck & ~state.door_open
        obstacles = grid.obstacles.clone()
        obstacles[:, config.door_cell] &= ~struck
        outcome = outcome._replace(goal_reward=outcome.goal_reward * config.goal_reward)
        return _with_door(grid._replace(obstacles=obstacles), state.door_open | struck), outcome

    def observe(self, state: StrikeState, key: torch.Tensor) -> torch.Tensor:
        if self.config.grid.is_paper_body:
            return proximity(state.cell, state.obstacles, self.config.size)
        return observe(state.grid, key, self.config.grid)

    def rewind(self, state: StrikeState) -> StrikeState:
        return state._replace(
            scatters=torch.zeros_like(state.scatters), ticks=torch.zeros_like(state.ticks)
        )

    def render(self, state: StrikeState, index: int = 0) -> str:
        """The grid's picture (``#`` wall, ``o`` obstacle, ``A`` agent, ``G`` goal), ``D`` the
        closed door."""
        picture = render_world(int(state.cell[index]), state.obstacles[index], self.config.size)
        if bool(state.door_open[index]):
            return picture
        lines = picture.split("\n")
        row, col = divmod(self.config.door_cell, self.config.size)
        line = lines[row + 1]
        lines[row + 1] = line[: col + 1] + "D" + line[col + 2 :]
        return "\n".join(lines)

    # -- optional parts of the World protocol ---------------------------------------------------

    def extra_observations(self, state: StrikeState, sensors: torch.Tensor) -> dict:
        """``proximity`` ``[S, 4]`` (the grid's N, W, S, E neighbours) and ``door_open``
        ``[S, 1]``: whether the door is open (for measurements; the agents read ``sensors``)."""
        near = sensors if self.config.grid.is_paper_body else None
        if near is None:
            near = proximity(state.cell, state.obstacles, self.config.size)
        return {"proximity": near, "door_open": state.door_open.unsqueeze(1)}

    def obstacle_map(self, state: StrikeState) -> torch.Tensor:
        """The obstacles (the door while closed), a bool copy ``[S, size, size]``."""
        size = self.config.size
        return state.obstacles.reshape(-1, size, size).clone()

    def to(self, device: torch.device | str) -> StrikeWorld:
        """Keep the layout on ``device``."""
        self._layout = self._layout.to(device)
        return self
