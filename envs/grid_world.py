"""The FactoredGrid world of the paper (SPEC sections 1-2): ``FactoredGrid``, its rules bound to
one ``WorldConfig`` behind the ``factorq_envs.protocol.World`` interface.

The parts live in two modules, whose names this one re-exports (import them from here):
``factorq_envs.grid_config`` (``WorldConfig``, the paper body's actions) and
``factorq_envs.grid_functions`` (the world's state and its pure, batched tensor functions, which
the compiled kernel mirrors).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    import numpy as np

from factorq_envs.grid_config import (  # noqa: F401 - the grid world's public names
    ACTION_NAMES,
    MAX_DISTRACTORS,
    NUM_ACTIONS,
    WorldConfig,
    check_choice,
    check_permutation,
)
from factorq_envs.grid_functions import (  # noqa: F401 - the grid world's public names
    COL_DELTA,
    MAX_LAYOUT_ATTEMPTS,
    ROW_DELTA,
    START_CELL,
    START_HEADING,
    StepOutcome,
    WorldState,
    _neighbour_cells,
    empty_state,
    is_reachable,
    neighbours,
    observe,
    proximity,
    render_world,
    reset_worlds,
    scatter_obstacles,
    sense,
    shortest_path_length,
    static_layout,
    step_worlds,
    where_rows,
)


class FactoredGrid:
    """The FactoredGrid world behind the ``factorq_envs.protocol.World`` interface: the functions of
    this module bound to one ``WorldConfig`` (the static layout drawn once, when needed).

    >>> from factorq_envs.protocol import World
    >>> grid = FactoredGrid(WorldConfig(size=3, num_obstacles=0, body="heading"))
    >>> isinstance(grid, World), grid.dependency.nonzero().tolist()
    (True, [[0, 0]])
    """

    def __init__(self, config: WorldConfig, static_obstacles: torch.Tensor | None = None) -> None:
        if not isinstance(config, WorldConfig):
            raise TypeError(f"config must be a WorldConfig, got {type(config).__name__}")
        self.config = config
        self._static = static_obstacles

    @property
    def dependency(self) -> torch.Tensor:
        return self.config.dependency

    @property
    def static_obstacles(self) -> torch.Tensor:
        """The static layout ``[N]`` (given, or drawn on first use)."""
        if self._static is None:
            self._static = static_layout(self.config)
        return self._static

    @static_obstacles.setter
    def static_obstacles(self, value: torch.Tensor) -> None:
        self._static = value

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> WorldState:
        return empty_state(batch, self.config.size, device, self.config.num_actuators)

    def reset(
        self,
        state: WorldState,
        mask: torch.Tensor,
        key: torch.Tensor,
        period: torch.Tensor,
        draws: torch.Tensor | None = None,
    ) -> WorldState:
        """``draws``: kept by ``step_keeping_draws`` for worlds whose episode terminated there
        (``reset_worlds``); the caller vouches that every world in ``mask`` is one."""
        if self._has_static_world(period):
            static = self.static_obstacles.to(state.cell.device)
        else:
            static = None  # no static world: no layout to draw, nothing to copy
        return reset_worlds(state, mask, key, period, static, self.config, draws)

    def step_keeping_draws(
        self, state: WorldState, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[WorldState, StepOutcome, torch.Tensor | None]:
        """``step`` and the scatter every world drew (``step_worlds(..., keep_draws=True)``)."""
        return step_worlds(state, action, key, period, self.config, keep_draws=True)

    def _has_static_world(self, period: torch.Tensor) -> bool:
        """Whether ``period`` holds a static world: read once per ``period`` tensor (a host
        synchronisation on a GPU), not at every reset; on ``meta`` (no data) assume one."""
        if period.device.type == "meta":
            return True
        if getattr(self, "_period_checked", None) is not period:
            self._period_checked = period
            self._period_has_static = bool((period == 0).any())
        return self._period_has_static

    def step(
        self, state: WorldState, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[WorldState, StepOutcome]:
        return step_worlds(state, action, key, period, self.config)

    def observe(self, state: WorldState, key: torch.Tensor) -> torch.Tensor:
        if self.config.is_paper_body:  # the same bits as ``observe``, without the offset tables
            return proximity(state.cell, state.obstacles, self.config.size)
        return observe(state, key, self.config)

    def rewind(self, state: WorldState) -> WorldState:
        """The scatter and sensor streams back at their start."""
        return state._replace(
            scatters=torch.zeros_like(state.scatters), ticks=torch.zeros_like(state.ticks)
        )

    def render(self, state: WorldState, index: int = 0) -> str:
        return render_world(int(state.cell[index]), state.obstacles[index], self.config.size)

    # -- optional parts of the World protocol ---------------------------------------------------

    def extra_observations(self, state: WorldState, sensors: torch.Tensor) -> dict:
        """``proximity`` ``[S, 4]`` bool (``keys.PROXIMITY``): the noise-free N, W, S, E
        neighbours, whatever the body (``sensors`` itself for the paper's body)."""
        if self.config.is_paper_body:
            return {"proximity": sensors}
        return {"proximity": proximity(state.cell, state.obstacles, self.config.size)}

    def obstacle_map(self, state: WorldState) -> torch.Tensor:
        """The obstacles, a bool copy ``[S, size, size]``."""
        size = self.config.size
        return state.obstacles.reshape(-1, size, size).clone()

    def render_rgb(self, state: WorldState, index: int = 0) -> np.ndarray:
        """World ``index`` as an image ``uint8 [H, W, 3]`` (``factorq_envs.render.render_rgb``)."""
        from factorq_envs.render import bumped_faces, render_rgb

        body = self.config.body_spec
        heading = int(state.heading[index])
        return render_rgb(
            int(state.cell[index]),
            state.obstacles[index].cpu().numpy(),
            self.config.size,
            heading=heading if body.has_heading else None,
            bumped=bumped_faces(state.bump[index].tolist(), heading, body),
        )

    def to(self, device: torch.device | str) -> FactoredGrid:
        """Keep the static layout (when drawn) on ``device``."""
        if self._static is not None:
            self._static = self._static.to(device)
        return self
