"""A grid world that pays: items on the floor, a positive local reward for the actuator that
collects one (issue 40, item 2; the paper's section 9: local rewards "positive as well as
negative").

The world is the paper's grid (``factorq_envs.grid_world.FactoredGrid``: its obstacles, walls,
goal, step and reset, run unchanged) with ``num_items`` items added on free cells. The body has
the paper's four translations and eight sensors: the grid's four proximity sensors (a wall or an
obstacle north, west, south, east) and four item sensors (an item on the neighbouring cell, same
order). An actuator that moves onto an item collects it: the item is gone and that actuator's
local reward is ``+item_reward``; an actuator that hits a wall or an obstacle collides, as in the
grid: the agent stays and its local reward is -1. So the local reward of actuator ``a`` has
either sign and is decided by two sensors, its proximity sensor and its item sensor
(``dependency`` ``[4, 8]``: ``a -> {a, 4 + a}``).

Items are drawn at every reset (layout number ``m`` of a world: the grid's own scatter,
``scatter_obstacles``, of ``num_items`` cells on the items' sub-stream ``SUBSTREAM_ITEMS`` of the
world's key, scatter index ``m``, so never on the start, the goal or the agent); an item drawn
under an obstacle, or covered by one that moves there, is hidden (not sensed, not collectable)
while the obstacle stays. Rewards: the grid's task reward (-1 per action, +1 at the goal), the
local reward vector as the outcome's ``collision`` (the field every world fills with its local
rewards, ``factorq_envs.protocol``), of either sign here; ``bump`` marks collisions only.

>>> from factorq_envs.protocol import World
>>> world = PayingGrid(PayingConfig(size=3, num_obstacles=0, num_items=0))
>>> isinstance(world, World), world.dependency.int().tolist()[0]
(True, [1, 0, 0, 0, 1, 0, 0, 0])
>>> state = paying_state(". $ .\\n. . .\\n. . .", cell=0)  # an item east of the agent
>>> key, period = torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64)
>>> world.observe(state, key).int().tolist()  # a wall north and west, an item east
[[1, 1, 0, 0, 0, 0, 0, 1]]
>>> state, outcome = world.step(state, torch.tensor([3]), key, period)  # east, onto the item
>>> outcome.collision.tolist(), int(state.items.sum())
([[0.0, 0.0, 0.0, 1.0]], 0)
>>> state, outcome = world.step(state, torch.tensor([0]), key, period)  # north, into the wall
>>> outcome.collision.tolist(), state.bump.int().tolist()
([[-1.0, 0.0, 0.0, 0.0]], [[1, 0, 0, 0]])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import torch

from factorq_envs.grid_world import (
    FactoredGrid,
    WorldConfig,
    WorldState,
    neighbours,
    render_world,
    scatter_obstacles,
    where_rows,
)
from factorq_torch.base.rng import substream_key
from factorq_torch.base.validation import check_float, check_int

if TYPE_CHECKING:
    import numpy as np

    from factorq_envs.gymnasium_env import FactoredGridGym

#: The items' sub-stream of a world's key (the grid's sub-streams are 1-4, ``base.rng``).
SUBSTREAM_ITEMS = 101
ITEM_SENSORS = ("item-north", "item-west", "item-south", "item-east")
#: An item's colour in ``render_rgb``.
ITEM_COLOUR = (230, 180, 20)


@dataclass(frozen=True)
class PayingConfig:
    """The parameters of a paying grid, validated on construction (the grid's own through its
    ``WorldConfig``)."""

    size: int = 10
    """Side of the square grid, in cells."""
    num_obstacles: int = 10
    """Single-cell obstacles, as the paper's grid."""
    num_items: int = 10
    """Items drawn at every reset (fewer show where an obstacle covers one)."""
    item_reward: float = 1.0
    """The local reward of collecting an item (> 0)."""
    max_steps: int = 10_000
    """Actions after which an episode is truncated."""
    layout_seed: int = 0
    """Seed of the static obstacle layout."""

    def __post_init__(self) -> None:
        grid = self.grid  # the grid's checks (size, obstacles, steps, seed)
        free = grid.num_cells - 3  # not the start, the goal or the agent
        check_int("num_items", self.num_items, 0, max(free, 0))
        check_float("item_reward", self.item_reward, 0.0, 1e6, low_open=True)

    @property
    def grid(self) -> WorldConfig:
        """The grid under the items: the paper's body and sensors."""
        return WorldConfig(
            size=self.size,
            num_obstacles=self.num_obstacles,
            max_steps=self.max_steps,
            layout_seed=self.layout_seed,
        )

    # What the env wrappers read (factorq_envs.protocol.CONFIG_FIELDS).
    num_actuators = 4
    num_headings = 1

    @property
    def num_sensors(self) -> int:
        return 8

    @property
    def num_cells(self) -> int:
        return self.size * self.size

    @property
    def goal_cell(self) -> int:
        return self.num_cells - 1

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return self.grid.actuator_names

    @property
    def sensor_names(self) -> tuple[str, ...]:
        return (*self.grid.sensor_names, *ITEM_SENSORS)

    @property
    def local_reward_range(self) -> tuple[float, float]:
        """The bounds of a local reward: -1 (a collision) to ``item_reward`` (an item); the env
        wrappers' ``collision`` spaces read it."""
        return (-1.0, float(self.item_reward))

    @property
    def dependency(self) -> torch.Tensor:
        """Bool ``[4, 8]``: actuator ``a``'s local reward is decided by its proximity sensor
        ``a`` (the collision) and its item sensor ``4 + a`` (the pay)."""
        eye = torch.eye(4, dtype=torch.bool)
        return torch.cat([eye, eye], dim=1)


class PayingState(NamedTuple):
    """``S`` paying grids: the grid's ``WorldState`` fields, then the items."""

    cell: torch.Tensor  # [S] int64
    obstacles: torch.Tensor  # [S, N] bool
    bump: torch.Tensor  # [S, 4] bool, collisions only
    episode_step: torch.Tensor  # [S] int64
    scatters: torch.Tensor  # [S] int64
    heading: torch.Tensor  # [S] int64 (always 0)
    ticks: torch.Tensor  # [S] int64
    items: torch.Tensor  # [S, N] bool, the items not collected yet
    item_layouts: torch.Tensor  # [S] int64, item layouts drawn so far (the stream's position)

    @property
    def grid(self) -> WorldState:
        return WorldState(*self[:7])


class PayingOutcome(NamedTuple):
    """What one step of ``S`` paying grids produced."""

    task_reward: torch.Tensor  # [S] float32: -1 per action, +1 more at the goal
    collision: torch.Tensor  # [S, 4] float32: the local rewards, -1 collided, +r collected
    terminated: torch.Tensor  # [S] bool
    truncated: torch.Tensor  # [S] bool
    collected: torch.Tensor  # [S] bool: the action collected an item

    @property
    def reward(self) -> torch.Tensor:
        """The conventional scalar reward: task + sum(local rewards)."""
        return self.task_reward + self.collision.sum(dim=-1)

    @property
    def local_reward(self) -> torch.Tensor:
        """``collision`` by its meaning here: the local reward vector, of either sign."""
        return self.collision


def paying_state(picture: str, cell: int) -> PayingState:
    """One paying grid from a picture (rows of ``.`` free, ``o`` obstacle, ``$`` item; spaces
    ignored), the agent on ``cell``: for examples and tests."""
    rows = [row.split() for row in picture.strip().splitlines()]
    flat = [mark for row in rows for mark in row]
    zero = torch.zeros(1, dtype=torch.int64)
    return PayingState(
        cell=torch.tensor([cell]),
        obstacles=torch.tensor([[mark == "o" for mark in flat]]),
        bump=torch.zeros(1, 4, dtype=torch.bool),
        episode_step=zero,
        scatters=zero,
        heading=zero,
        ticks=zero,
        items=torch.tensor([[mark == "$" for mark in flat]]),
        item_layouts=zero,
    )


class PayingGrid:
    """``S`` paying grids as pure batched functions (``factorq_envs.protocol.World``): the
    grid's (``FactoredGrid``) plus the items (module docstring)."""

    def __init__(self, config: PayingConfig | None = None) -> None:
        if config is None:
            config = PayingConfig()
        if not isinstance(config, PayingConfig):
            raise TypeError(f"config must be a PayingConfig, got {type(config).__name__}")
        self.config = config
        self.grid = FactoredGrid(config.grid)

    @property
    def dependency(self) -> torch.Tensor:
        return self.config.dependency

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> PayingState:
        grid = self.grid.initial_state(batch, device)
        return PayingState(
            *grid,
            items=torch.zeros_like(grid.obstacles),
            item_layouts=torch.zeros_like(grid.cell),
        )

    def _visible(self, state: PayingState) -> torch.Tensor:
        """The items an obstacle does not cover ``[S, N]``."""
        return state.items & ~state.obstacles

    def reset(
        self, state: PayingState, mask: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> PayingState:
        grid = self.grid.reset(state.grid, mask, key, period)
        config = self.config
        items = state.items
        if config.num_items:
            fresh = scatter_obstacles(
                substream_key(key, SUBSTREAM_ITEMS),
                state.item_layouts,
                grid.cell,
                config.size,
                config.num_items,
            )
            items = where_rows(mask, fresh, items)
        return PayingState(*grid, items=items, item_layouts=state.item_layouts + mask)

    def step(
        self, state: PayingState, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[PayingState, PayingOutcome]:
        visible = self._visible(state)  # before the step's scatter moves obstacles
        grid, outcome = self.grid.step(state.grid, action, key, period)
        moved = grid.cell != state.cell  # a collision leaves the agent in place
        collected = moved & visible.gather(1, grid.cell.unsqueeze(1)).squeeze(1)  # [S]
        items = state.items.clone()
        items[torch.arange(items.shape[0], device=items.device), grid.cell] &= ~collected
        actuators = torch.arange(self.config.num_actuators, device=action.device)
        paid = (actuators == action.unsqueeze(1)) & collected.unsqueeze(1)  # [S, 4]
        local = outcome.collision.masked_fill(paid, float(self.config.item_reward))
        result = PayingOutcome(
            task_reward=outcome.task_reward,
            collision=local,
            terminated=outcome.terminated,
            truncated=outcome.truncated,
            collected=collected,
        )
        return PayingState(*grid, items=items, item_layouts=state.item_layouts), result

    def observe(self, state: PayingState, key: torch.Tensor) -> torch.Tensor:
        """The grid's proximity sensors, then the item sensors (N, W, S, E): ``[S, 8]`` bool."""
        proximity = self.grid.observe(state.grid, key)  # [S, 4]
        target, inside = neighbours(state.cell, self.config.size)  # [S, 4]
        items = inside & self._visible(state).gather(1, target)
        return torch.cat([proximity, items], dim=1)

    def rewind(self, state: PayingState) -> PayingState:
        grid = self.grid.rewind(state.grid)
        return PayingState(*grid, items=state.items, item_layouts=torch.zeros_like(state.cell))

    def render(self, state: PayingState, index: int = 0) -> str:
        """The grid's picture (``#`` wall, ``o`` obstacle, ``A`` agent, ``G`` goal) with ``$``
        on every visible item."""
        picture = render_world(int(state.cell[index]), state.obstacles[index], self.config.size)
        lines = [list(line) for line in picture.splitlines()]
        size = self.config.size
        for cell in self._visible(state)[index].nonzero().flatten().tolist():
            row, col = divmod(cell, size)
            if lines[row + 1][col + 1] == ".":
                lines[row + 1][col + 1] = "$"
        return "\n".join("".join(line) for line in lines)

    def render_rgb(self, state: PayingState, index: int = 0) -> np.ndarray:
        """The grid's image (``FactoredGrid.render_rgb``) with a gold square on every visible
        item, ``uint8 [H, W, 3]``."""
        from factorq_envs.render import SCALE

        image = self.grid.render_rgb(state.grid, index).copy()
        quarter = SCALE // 4
        for cell in self._visible(state)[index].nonzero().flatten().tolist():
            row, col = divmod(cell, self.config.size)
            top, left = (row + 1) * SCALE + quarter, (col + 1) * SCALE + quarter
            image[top : top + 2 * quarter, left : left + 2 * quarter] = ITEM_COLOUR
        return image

    def obstacle_map(self, state: PayingState) -> torch.Tensor:
        return self.grid.obstacle_map(state.grid)

    def extra_observations(self, state: PayingState, sensors: torch.Tensor) -> dict:
        """``proximity`` ``[S, 4]``: the first four sensors (as the grid's)."""
        return {"proximity": sensors[:, :4]}

    def to(self, device: torch.device | str) -> PayingGrid:
        self.grid.to(device)
        return self


def paying_gym(
    obstacle_period: int = 0, render_mode: str | None = None, **config: Any
) -> FactoredGridGym:
    """One paying grid as a Gymnasium env (``FactoredGridGym(world=PayingGrid(...))``), the
    entry point of the id ``"PayingGrid-v0"`` (registered on ``import factorq_envs``):
    ``config`` holds ``PayingConfig``'s fields.

    >>> import gymnasium, factorq_envs
    >>> env = gymnasium.make("PayingGrid-v0", size=4, num_obstacles=0, num_items=3)
    >>> env.observation_space["collision"]
    Box(-1.0, 1.0, (4,), float32)
    """
    from factorq_envs.gymnasium_env import FactoredGridGym

    world = PayingGrid(PayingConfig(**config))
    return FactoredGridGym(world=world, obstacle_period=obstacle_period, render_mode=render_mode)
