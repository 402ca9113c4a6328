"""The World protocol: what a world offers the env wrappers, the experiments and the fast path.

A world is pure batched functions over a state of tensors with a leading dimension ``S`` of
independent worlds, plus the data that describes its body (``dependency``).
``factorq_envs.grid_world``'s ``FactoredGrid`` implements it for the paper's grid;
``factorq_envs.corridor``'s ``Corridor`` is a second, one-dimensional world. A new world is one new
file with a class like them: the torchrl env
(``factorq_envs.torchrl_env.FactoredGridEnv(world=...)``) and the gymnasium env
(``factorq_envs.gymnasium_env.FactoredGridGym(world=...)``) read their specs from it, and
``SplitLocalReward``, the agents and the trainers' modular path run it unchanged. The compiled fast
path runs only ``FactoredGrid``: the trainers fall back to the modular path for any other world.

What the wrappers read, besides the methods below:

- ``config``: ``num_cells`` (the ``cell`` observation is in ``[0, num_cells)``), ``num_sensors``
  (``K``), ``num_actuators`` (``A``), ``num_headings`` (1: no ``heading`` in the observation),
  ``goal_cell``, ``max_steps`` and ``actuator_names`` (error messages); optionally
  ``local_reward_range`` ``(low, high)``, the bounds of the ``collision`` entry (default
  ``(-1.0, 0.0)``: collisions only; ``factorq_envs.paying_grid`` pays up to ``+item_reward``);
- the state (a ``NamedTuple`` of tensors, leading dimension ``S``): ``cell`` ``[S]`` int64,
  ``bump`` ``[S, A]`` bool, ``episode_step`` ``[S]`` int64, and ``heading`` ``[S]`` int64 when
  ``num_headings > 1``;
- the step's outcome (a ``NamedTuple``): ``reward`` ``[S]`` (the conventional scalar reward),
  ``task_reward`` ``[S]`` (the reward without the collisions), ``collision`` ``[S, A]`` float32
  (the local reward vector), ``terminated`` and ``truncated`` ``[S]`` bool.

Optional methods, used when a world has them: ``extra_observations(state, sensors)`` (more
observation entries, ``{key: [S, n] bool}``: the grid's ``proximity``), ``obstacle_map(state)``,
``render_rgb(state, index)``, ``to(device)`` (move constant tensors the world holds) and
``step_keeping_draws(state, action, key, period)`` (``step`` plus what it drew at random,
``[S, ...]``, that ``reset(state, mask, key, period, draws=...)`` reuses for the worlds whose
episode that step terminated: the grid's scatter, so that the torchrl env's reset after
terminated episodes draws nothing again). Nothing here imports a world.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, runtime_checkable

import torch

#: The fields of a world's ``config`` that the wrappers read.
CONFIG_FIELDS = (
    "num_cells",
    "num_sensors",
    "num_actuators",
    "num_headings",
    "goal_cell",
    "max_steps",
    "actuator_names",
)


@dataclass(frozen=True)
class EnvSizes:
    """The sizes an agent is built from, for an env that is not a ``World`` (a declared
    Gymnasium env, ``factorq_envs.gymnasium_adapter``): the ``CONFIG_FIELDS`` of a world's
    ``config``, so ``env.config.num_sensors`` reads the same on every env of the project.
    ``goal_cell`` and ``max_steps`` are ``None`` where the env has none (or does not say)."""

    num_cells: int
    num_sensors: int
    num_actuators: int
    num_headings: int = 1
    goal_cell: int | None = None
    max_steps: int | None = None
    actuator_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        from factorq_torch.base.validation import check_int

        check_int("num_cells", self.num_cells, 1)
        check_int("num_sensors", self.num_sensors, 1)
        check_int("num_actuators", self.num_actuators, 1)
        check_int("num_headings", self.num_headings, 1)
        if len(self.actuator_names) != self.num_actuators:
            raise ValueError(
                f"actuator_names={self.actuator_names!r} names {len(self.actuator_names)} "
                f"actuators, but num_actuators={self.num_actuators}"
            )


@runtime_checkable
class World(Protocol):
    """``S`` independent worlds as pure functions (inputs are never mutated)."""

    config: Any
    """The parameters (a frozen, validated dataclass), including the body and its sensors."""

    @property
    def dependency(self) -> torch.Tensor:
        """Bool ``[actuators, sensors]``: which sensors decide each actuator's local reward."""

    def initial_state(self, batch: int, device: torch.device | str | None = None) -> NamedTuple:
        """``batch`` worlds before their first ``reset``."""

    def reset(
        self, state: NamedTuple, mask: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> NamedTuple:
        """Start new episodes where ``mask`` ``[S]`` is True (``period`` ``[S]``: each world's
        obstacle period, 0 static; ``key`` ``[S]`` int64: each world's random stream)."""

    def step(
        self, state: NamedTuple, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[NamedTuple, NamedTuple]:
        """One action per world: ``(new state, outcome)`` (rewards, collision vector, flags)."""

    def observe(self, state: NamedTuple, key: torch.Tensor) -> torch.Tensor:
        """All sensors as the agent receives them, ``[S, K]`` bool."""

    def rewind(self, state: NamedTuple) -> NamedTuple:
        """``state`` with its random streams back at their start (a new seed replays exactly)."""

    def render(self, state: NamedTuple, index: int = 0) -> str:
        """A text picture of world ``index``."""


def check_world(world: Any, name: str = "world") -> Any:
    """``world`` if it implements ``World`` (methods and the ``config`` fields the wrappers
    read), else one TypeError naming what is missing."""
    missing = [
        method
        for method in ("initial_state", "reset", "step", "observe", "rewind", "render")
        if not callable(getattr(world, method, None))
    ]
    if not hasattr(world, "dependency"):
        missing.append("dependency")
    config = getattr(world, "config", None)
    if config is None:
        missing.append("config")
    else:
        missing += [f"config.{field}" for field in CONFIG_FIELDS if not hasattr(config, field)]
    if missing:
        raise TypeError(
            f"{name} must implement factorq_envs.protocol.World, got {type(world).__name__} "
            f"without {', '.join(missing)}"
        )
    return world


def optional_method(world: Any, method: str) -> Callable[..., Any]:
    """``world``'s optional ``method`` (``extra_observations``, ``obstacle_map``, ``render_rgb``,
    ``to``), or a TypeError naming the world that lacks it."""
    found = getattr(world, method, None)
    if not callable(found):
        raise TypeError(
            f"{type(world).__name__} has no {method}(): this world does not offer it "
            f"(factorq_envs.protocol lists the optional methods)"
        )
    return found
