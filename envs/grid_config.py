"""The parameters of one FactoredGrid world (SPEC section 1): ``WorldConfig``, validated on
construction, with the checks of its named choices and sensor order, and the paper body's actions.

The world's rules are ``factorq_envs.grid_functions``; ``factorq_envs.grid_world`` binds them to a
``WorldConfig`` (``FactoredGrid``) and re-exports the names of both modules.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, cast

import torch

from factorq_envs.body import (
    BODIES,
    SENSOR_LAYOUTS,
    TRANSLATE,
    Body,
    SensorLayout,
    base_dependency,
    draw_permutation,
    sensor_offsets,
)
from factorq_torch.base.validation import check_float, check_int, is_int

#: The paper's body (``factorq_envs.body.TRANSLATE``): its actions, in the paper's order.
ACTION_NAMES = TRANSLATE.actuators
NUM_ACTIONS = len(ACTION_NAMES)
#: The most distractor bits a world may add.
MAX_DISTRACTORS = 32


def check_choice(name: str, value: object, allowed: Collection[str]) -> str:
    """``value`` if it is one of the names ``allowed``, else a ValueError naming them."""
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{name}={value!r} is unknown: choose one of {', '.join(allowed)}")
    return value


def check_permutation(name: str, value: Any, count: int) -> tuple[int, ...]:
    """``value`` as a tuple if it is a permutation of ``range(count)``, else an error naming it."""
    if isinstance(value, str) or not hasattr(value, "__iter__"):
        raise TypeError(
            f"{name} must be None, an int seed or a sequence of ints, got {value!r} "
            f"({type(value).__name__})"
        )
    values = tuple(value.tolist() if isinstance(value, torch.Tensor) else value)
    if not all(is_int(v) for v in values) or sorted(values) != list(range(count)):
        raise ValueError(
            f"{name}={values!r} is not a permutation: must hold each of 0..{count - 1} once "
            f"({count} sensors)"
        )
    return values


@dataclass(frozen=True)
class WorldConfig:
    """The parameters of one FactoredGrid world, validated on construction.

    Args:
        size: side of the square grid in cells, >= 2.
        num_obstacles: single-cell obstacles.
        obstacle_period: 0 static, 10 semi-dynamic, 1 dynamic (scatter after every k-th action).
        max_steps: actions after which an episode is truncated.
        layout_seed: seed of the static layout.
        body: ``"translate"`` (the paper) or ``"heading"`` (``factorq_envs.body.BODIES``).
        sensors: ``"cross"`` (the paper) or ``"ring"`` (``factorq_envs.body.SENSOR_LAYOUTS``).
        num_distractors: extra sensor bits that carry no information.
        sensor_permutation: the sensors' order: None, a permutation or an int seed to draw one.
        sensor_noise: probability that each sensor bit is flipped.
        actuator_noise: probability that another actuator fires than the chosen one.
    """

    size: int = 10
    """Side of the square grid, in cells (the wall surrounds it)."""
    num_obstacles: int = 10
    """Single-cell obstacles; never on start, goal or the agent, never two on one cell."""
    obstacle_period: int = 0
    """0 static (one fixed layout), 10 semi-dynamic, 1 dynamic: scatter after every k-th action."""
    max_steps: int = 10_000
    """Actions after which an episode is truncated."""
    layout_seed: int = 0
    """Seed of the static layout (the same for every world of a batch)."""
    body: str = "translate"
    """The agent's body: translate (the paper: 4 moves N/W/S/E) or heading (forward, turn-left,
    turn-right; sensors turn with the heading)."""
    sensors: str = "cross"
    """Sensor layout: cross (the paper: the 4 neighbours) or ring (the 8 neighbours)."""
    num_distractors: int = 0
    """Extra sensor bits that carry no information: fair coins drawn afresh at every observation."""
    sensor_permutation: Sequence[int] | int | None = None
    """The order the agent receives the sensors in: None (layout order, distractors last), a
    permutation (agent's sensor j = sensor permutation[j]) or an int seed to draw one from."""
    sensor_noise: float = 0.0
    """Probability that each sensor bit is flipped, independently at every observation."""
    actuator_noise: float = 0.0
    """Probability that another actuator (uniform among the others) fires than the chosen one."""

    def __post_init__(self) -> None:
        check_int("size", self.size, 2)
        check_int(
            "num_obstacles",
            self.num_obstacles,
            0,
            self.max_obstacles,
            f" for a {self.size}x{self.size} grid with start, goal and agent kept free",
        )
        check_int("obstacle_period", self.obstacle_period, 0, hint=" (0 static, k > 0 moving)")
        check_int("max_steps", self.max_steps, 1)
        check_int("layout_seed", self.layout_seed, 0)
        check_choice("body", self.body, BODIES)
        check_choice("sensors", self.sensors, SENSOR_LAYOUTS)
        check_int("num_distractors", self.num_distractors, 0, MAX_DISTRACTORS)
        check_float("sensor_noise", self.sensor_noise, 0.0, 1.0)
        check_float("actuator_noise", self.actuator_noise, 0.0, 1.0)
        count = SENSOR_LAYOUTS[self.sensors].num_sensors + self.num_distractors
        permutation = self.sensor_permutation
        if permutation is not None:
            if is_int(permutation):
                permutation = draw_permutation(count, permutation)
            permutation = check_permutation("sensor_permutation", permutation, count)
            if permutation == tuple(range(count)):
                permutation = None  # the identity is the layout order: one spelling only
        object.__setattr__(self, "sensor_permutation", permutation)

    @property
    def body_spec(self) -> Body:
        """The declaration of ``body`` (``factorq_envs.body``)."""
        return BODIES[self.body]

    @property
    def layout(self) -> SensorLayout:
        """The declaration of the sensor layout ``sensors`` (``factorq_envs.body``)."""
        return SENSOR_LAYOUTS[self.sensors]

    @property
    def num_actuators(self) -> int:
        return self.body_spec.num_actuators

    @property
    def num_headings(self) -> int:
        """4 for a body with a heading, else 1."""
        return self.body_spec.num_headings

    @property
    def num_sensors(self) -> int:
        """``K``: layout sensors plus distractors, all of which the agent receives."""
        return self.layout.num_sensors + self.num_distractors

    @property
    def permutation(self) -> tuple[int, ...]:
        """Agent's sensor ``j`` is sensor ``permutation[j]`` of the layout order (identity when
        ``sensor_permutation`` is None)."""
        if self.sensor_permutation is None:
            return tuple(range(self.num_sensors))
        return cast(tuple[int, ...], self.sensor_permutation)  # a tuple after __post_init__

    @property
    def sensor_names(self) -> tuple[str, ...]:
        """The names of the sensors in the order the agent receives them."""
        names = self.layout.names(self.body_spec)
        names += tuple(f"distractor-{d}" for d in range(self.num_distractors))
        return tuple(names[k] for k in self.permutation)

    @property
    def actuator_names(self) -> tuple[str, ...]:
        return self.body_spec.actuators

    @property
    def dependency(self) -> torch.Tensor:
        """Ground truth bool ``[actuators, sensors]`` (sensors in the agent's order): True where
        the sensor decides the actuator's local (collision) reward."""
        return base_dependency(self.body_spec, self.layout, self.num_distractors)[
            :, list(self.permutation)
        ]

    @property
    def is_paper_body(self) -> bool:
        """The paper's body and sensors exactly: translate, cross, no distractors, no
        permutation, no noise (what the compiled fast path runs)."""
        return (
            self.body == "translate"
            and self.sensors == "cross"
            and self.num_distractors == 0
            and self.sensor_permutation is None
            and self.sensor_noise == 0.0
            and self.actuator_noise == 0.0
        )

    @cached_property
    def _tables(self) -> dict[str, torch.Tensor]:
        """Constant tensors of the body (CPU; moved to the state's device where used)."""
        body = self.body_spec
        return {
            "offsets": sensor_offsets(self.layout),  # [4, layout sensors, 2]
            "moves": torch.tensor([-1 if m is None else m for m in body.moves]),  # [A]
            "turns": torch.tensor(body.turns),  # [A]
            "permutation": torch.tensor(self.permutation),  # [K]
        }

    @property
    def num_cells(self) -> int:
        return self.size * self.size

    @property
    def goal_cell(self) -> int:
        return self.num_cells - 1

    @property
    def max_obstacles(self) -> int:
        return self.size * self.size - 3
