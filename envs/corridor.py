"""A second world in one file: a corridor with hurdles (the ``factorq_envs.protocol.World``
interface).

The agent walks a one-dimensional corridor of ``length`` cells from cell 0 to the goal, cell
``length - 1``. Some cells hold a hurdle. Its body has three actuators: ``back`` (one cell back),
``forward`` (one cell ahead) and ``jump`` (two cells ahead, flying over the cell between); an
actuator whose target cell is a hurdle or outside the corridor collides: the agent stays and
that actuator's local reward is -1. Its four sensors read whether a cell is a hurdle or outside:
``behind`` (c - 1), ``ahead`` (c + 1), ``ahead-2`` (c + 2) and ``ahead-3`` (c + 3), which no
actuator reaches. So the dependency is not the grid's: three actuators, four sensors, one sensor
that decides nothing.

Hurdles are never on the start, the goal or the agent, and never on two neighbouring cells, so a
``forward`` or a ``jump`` always leads on. A layout puts a hurdle on cell ``c`` (1 .. length - 2,
left to right) when the draw of ``c`` is below ``probability_threshold(density)``, unless cell
``c - 1`` already holds one or the agent stands on ``c``. Layout number ``m`` of a world uses
counters ``m * length + c`` of its key. A static world (period 0) has the layout of
``layout_seed``; a moving one (period ``k > 0``) draws a new layout at every reset and after
every ``k``-th action of an episode (except the one that reaches the goal), as the grid does.

Rewards: -1 per action, +1 on reaching the goal, the collision vector as the local reward.

>>> from factorq_envs.protocol import World
>>> corridor = Corridor(CorridorConfig(length=6, density=0.0))
>>> isinstance(corridor, World), corridor.dependency.int().tolist()
(True, [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]])
>>> key, period = torch.zeros(1, dtype=torch.int64), torch.zeros(1, dtype=torch.int64)
>>> state = corridor.reset(corridor.initial_state(1), torch.ones(1, dtype=bool), key, period)
>>> state, outcome = corridor.step(state, torch.tensor([2]), key, period)  # jump
>>> print(corridor.render(state))
#..A..G#
>>> state, outcome = corridor.step(state, torch.tensor([2]), key, period)  # to cell 4
>>> state, outcome = corridor.step(state, torch.tensor([2]), key, period)  # past the end
>>> outcome.collision.tolist(), corridor.observe(state, key).int().tolist()
([[0.0, 0.0, -1.0]], [[0, 0, 1, 1]])
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from factorq_torch.base.rng import STREAM_LAYOUT, derive_keys, probability_threshold, random_bits
from factorq_torch.base.validation import check_float, check_int

ACTUATORS = ("back", "forward", "jump")
#: The cell each actuator moves to, relative to the agent.
MOVES = (-1, 1, 2)
SENSORS = ("behind", "ahead", "ahead-2", "ahead-3")
#: The cell each sensor reads, relative to the agent.
SENSOR_OFFSETS = (-1, 1, 2, 3)


@dataclass(frozen=True)
class CorridorConfig:
    """The parameters of a corridor, validated on construction."""

    length: int = 12
    """Cells of the corridor (>= 3): start 0, goal ``length - 1``."""
    density: float = 0.4
    """Probability that a free cell gets a hurdle (before the no-neighbours rule)."""
    max_steps: int = 1_000
    """Actions after which an episode is truncated."""
    layout_seed: int = 0
    """Seed of the static layout."""

    def __post_init__(self) -> None:
        check_int("length", self.length, 3, 4096)
        check_float("density", self.density, 0.0, 1.0)
        check_int("max_steps", self.max_steps, 1)
        check_int("layout_seed", self.layout_seed, 0)

    # What the env wrappers read (factorq_envs.protocol.CONFIG_FIELDS).
    num_sensors = len(SENSORS)
    num_actuators = len(ACTUATORS)
    num_headings = 1
    actuator_names = ACTUATORS
    sensor_names = SENSORS

    @property
    def num_cells(self) -> int:
        return self.length

    @property
    def goal_cell(self) -> int:
        return self.length - 1

    @property
    def dependency(self) -> torch.Tensor:
        """Bool ``[3, 4]``: each actuator's collision is decided by the sensor reading its
        target cell; ``ahead-3`` decides nothing."""
        return torch.tensor([[offset == move for offset in SENSOR_OFFSETS] for move in MOVES])


class CorridorState(NamedTuple):
    """``S`` corridors (leading dimension ``S``)."""

    cell: torch.Tensor  # [S] int64
    hurdles: torch.Tensor  # [S, L] bool
    bump: torch.Tensor  # [S, 3] bool, the actuator whose last firing collided
    episode_step: torch.Tensor  # [S] int64
    layouts: torch.Tensor  # [S] int64, layouts drawn so far (the stream's position)


class CorridorOutcome(NamedTuple):
    """What one step of ``S`` corridors produced."""

    task_reward: torch.Tensor  # [S] float32: -1 per action, +1 more on reaching the goal
    collision: torch.Tensor  # [S, 3] float32: -1 on the actuator that collided
    terminated: torch.Tensor  # [S] bool
    truncated: torch.Tensor  # [S] bool

    @property
    def reward(self) -> torch.Tensor:
        """The conventional scalar reward: task + sum(collision)."""
        return self.task_reward + self.collision.sum(dim=-1)


def draw_hurdles(
    key: torch.Tensor, layout: torch.Tensor, agent: torch.Tensor, config: CorridorConfig
) -> torch.Tensor:
    """Layout number ``layout`` ``[S]`` of each world ``[S]`` with the agent on ``agent``:
    hurdles ``[S, L]`` bool (the rule of the module docstring)."""
    length = config.length
    cells = torch.arange(length, device=agent.device)
    bits = random_bits(key.unsqueeze(1), layout.unsqueeze(1) * length + cells)  # [S, L]
    wanted = bits < probability_threshold(config.density)
    hurdles = torch.zeros_like(wanted)
    for cell in range(1, length - 1):
        free = ~hurdles[:, cell - 1] & (agent != cell)
        hurdles[:, cell] = wanted[:, cell] & free
    return hurdles


def blocked(cell: torch.Tensor, hurdles: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Whether the cells at ``offsets`` ``[n]`` from ``cell`` ``[S]`` are hurdles or outside:
    ``[S, n]`` bool."""
    length = hurdles.shape[1]
    target = cell.unsqueeze(1) + offsets
    inside = (target >= 0) & (target < length)
    return ~inside | hurdles.gather(1, target.clamp(0, length - 1))


class Corridor:
    """``S`` corridors as pure batched functions (``factorq_envs.protocol.World``)."""

    def __init__(self, config: CorridorConfig | None = None) -> None:
        if config is None:
            config = CorridorConfig()
        if not isinstance(config, CorridorConfig):
            raise TypeError(f"config must be a CorridorConfig, got {type(config).__name__}")
        self.config = config
        self._layout_key = derive_keys(config.layout_seed, STREAM_LAYOUT, 1)  # [1]

    @property
    def dependency(self) -> torch.Tensor:
        return self.config.dependency

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> CorridorState:
        zeros = torch.zeros(batch, dtype=torch.int64, device=device)
        return CorridorState(
            cell=zeros.clone(),
            hurdles=torch.zeros(batch, self.config.length, dtype=torch.bool, device=device),
            bump=torch.zeros(batch, len(ACTUATORS), dtype=torch.bool, device=device),
            episode_step=zeros.clone(),
            layouts=zeros.clone(),
        )

    def _relayout(
        self,
        state: CorridorState,
        where: torch.Tensor,
        key: torch.Tensor,
        agent: torch.Tensor,
        layouts: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """New hurdles where ``where`` ``[S]`` is True (layout number ``layouts`` of ``key``)."""
        fresh = draw_hurdles(key, layouts, agent, self.config)
        hurdles = torch.where(where.unsqueeze(1), fresh, state.hurdles)
        return hurdles, layouts + where.to(torch.int64)

    def reset(
        self, state: CorridorState, mask: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> CorridorState:
        start = torch.zeros_like(state.cell)
        moving = mask & (period > 0)
        hurdles, layouts = self._relayout(state, moving, key, start, state.layouts)
        static = draw_hurdles(
            self._layout_key.to(start.device).expand_as(start),
            torch.zeros_like(start),
            start,
            self.config,
        )
        hurdles = torch.where((mask & (period == 0)).unsqueeze(1), static, hurdles)
        return CorridorState(
            cell=torch.where(mask, 0, state.cell),
            hurdles=hurdles,
            bump=state.bump & ~mask.unsqueeze(1),
            episode_step=torch.where(mask, 0, state.episode_step),
            layouts=layouts,
        )

    def step(
        self, state: CorridorState, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[CorridorState, CorridorOutcome]:
        moves = torch.tensor(MOVES, device=action.device)
        collided = blocked(state.cell, state.hurdles, moves).gather(1, action.unsqueeze(1))
        collided = collided.squeeze(1)  # [S]
        cell = torch.where(collided, state.cell, state.cell + moves[action])
        actuators = torch.arange(len(ACTUATORS), device=action.device)
        bump = (actuators == action.unsqueeze(1)) & collided.unsqueeze(1)
        episode_step = state.episode_step + 1
        terminated = cell == self.config.goal_cell
        truncated = ~terminated & (episode_step >= self.config.max_steps)
        outcome = CorridorOutcome(
            task_reward=terminated.to(torch.float32) - 1.0,
            collision=torch.where(bump, -1.0, 0.0),
            terminated=terminated,
            truncated=truncated,
        )
        relayout = (period > 0) & ~terminated & (episode_step % period.clamp(min=1) == 0)
        hurdles, layouts = state.hurdles, state.layouts
        if bool(relayout.any()):
            hurdles, layouts = self._relayout(state, relayout, key, cell, layouts)
        return CorridorState(cell, hurdles, bump, episode_step, layouts), outcome

    def observe(self, state: CorridorState, key: torch.Tensor) -> torch.Tensor:
        offsets = torch.tensor(SENSOR_OFFSETS, device=state.cell.device)
        return blocked(state.cell, state.hurdles, offsets)  # [S, 4]

    def rewind(self, state: CorridorState) -> CorridorState:
        return state._replace(layouts=torch.zeros_like(state.layouts))

    def render(self, state: CorridorState, index: int = 0) -> str:
        """``#`` the ends, ``o`` a hurdle, ``A`` the agent, ``G`` the goal."""
        cell, hurdles = int(state.cell[index]), state.hurdles[index].tolist()
        picture = [
            "A" if c == cell else "G" if c == self.config.goal_cell else "o" if h else "."
            for c, h in enumerate(hurdles)
        ]
        return "#" + "".join(picture) + "#"

    def obstacle_map(self, state: CorridorState) -> torch.Tensor:
        """The hurdles, a bool copy ``[S, L]``."""
        return state.hurdles.clone()
