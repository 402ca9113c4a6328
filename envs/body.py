"""Bodies and sensor layouts of the grid world: the body is data (DESIGN section 1).

A **body** declares its actuators: the direction each one moves in (relative to the heading, or
none) and the quarter turns it adds to the heading. A **sensor layout** declares its sensors: the
cell each one looks at, as an offset from the agent in the frame of heading 0 (north up). With
distractors and a permutation they make the sensors the agent receives, and from those follows
``dependency``: bool ``[actuators, sensors]``, True where the sensor decides the actuator's local
(collision) reward. Nothing else in the project assumes the paper's pairing "sensor i belongs to
actuator i" or four of anything: that pairing is written here, in ``TRANSLATE`` and ``CROSS``.

Directions are numbered as the paper's actions: 0 north, 1 west, 2 south, 3 east; a quarter turn
to the left adds 1 (north -> west -> south -> east -> north). An offset ``(d_row, d_col)`` turned
left by a quarter becomes ``(-d_col, d_row)``.

A new body or layout is one new entry: a ``Body(...)`` in ``BODIES`` or a ``SensorLayout(...)`` in
``SENSOR_LAYOUTS``; a new world is one new file implementing ``factorq_envs.protocol.World``
(``factorq_envs.corridor``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from factorq_torch.base.rng import SUBSTREAM_PERMUTATION, random_bits_int, substream_key_int
from factorq_torch.base.validation import check_int

#: Quarter turns a full turn has; headings are directions in [0, NUM_HEADINGS).
NUM_HEADINGS = 4


@dataclass(frozen=True)
class Body:
    """What an agent's actuators do.

    ``moves[a]``: the direction actuator ``a`` moves in, relative to the heading (0 ahead, 1 left,
    2 behind, 3 right), or ``None`` when it does not move (and so can never collide);
    ``turns[a]``: quarter turns to the left it adds to the heading. ``has_heading``: the heading is
    part of the state (and of the observation); without it the heading stays 0 (north).
    """

    name: str
    actuators: tuple[str, ...]
    moves: tuple[int | None, ...]
    turns: tuple[int, ...]
    has_heading: bool
    sensor_prefix: tuple[str, ...]
    """Names of the four directions in this body's frame (ahead, left, behind, right)."""

    @property
    def num_actuators(self) -> int:
        return len(self.actuators)

    @property
    def num_headings(self) -> int:
        return NUM_HEADINGS if self.has_heading else 1


#: The paper's body: four translations, always facing north (so relative = absolute directions).
TRANSLATE = Body(
    name="translate",
    actuators=("north", "west", "south", "east"),
    moves=(0, 1, 2, 3),
    turns=(0, 0, 0, 0),
    has_heading=False,
    sensor_prefix=("north", "west", "south", "east"),
)
#: A body that faces one of four directions: forward moves ahead (the only actuator that can
#: collide), the turns change the heading in place.
HEADING = Body(
    name="heading",
    actuators=("forward", "turn-left", "turn-right"),
    moves=(0, None, None),
    turns=(0, 1, 3),
    has_heading=True,
    sensor_prefix=("front", "left", "back", "right"),
)
BODIES = {body.name: body for body in (TRANSLATE, HEADING)}


@dataclass(frozen=True)
class SensorLayout:
    """Proximity sensors: sensor ``k`` is 1 when the cell at ``offsets[k]`` (rows, columns in the
    frame of heading 0, turned with the heading) is wall or obstacle. ``directions[k]`` names it
    from the body's frame: indices into ``Body.sensor_prefix``, joined by ``-``."""

    name: str
    offsets: tuple[tuple[int, int], ...]
    directions: tuple[tuple[int, ...], ...]

    @property
    def num_sensors(self) -> int:
        return len(self.offsets)

    def names(self, body: Body) -> tuple[str, ...]:
        return tuple(
            "-".join(body.sensor_prefix[d] for d in direction) for direction in self.directions
        )


#: The paper's four neighbours, in direction order: sensor k looks in direction k.
CROSS = SensorLayout(
    name="cross",
    offsets=((-1, 0), (0, -1), (1, 0), (0, 1)),
    directions=((0,), (1,), (2,), (3,)),
)
#: The eight neighbours: the cross first (so sensor k < 4 still looks in direction k), then the
#: diagonals ahead-left, behind-left, behind-right, ahead-right.
RING = SensorLayout(
    name="ring",
    offsets=(*CROSS.offsets, (-1, -1), (1, -1), (1, 1), (-1, 1)),
    directions=(*CROSS.directions, (0, 1), (2, 1), (2, 3), (0, 3)),
)
SENSOR_LAYOUTS = {layout.name: layout for layout in (CROSS, RING)}


def turn_offset(offset: tuple[int, int], quarter_turns: int) -> tuple[int, int]:
    """``offset`` turned left by ``quarter_turns`` quarters: ``(r, c) -> (-c, r)`` each."""
    d_row, d_col = offset
    for _ in range(quarter_turns % NUM_HEADINGS):
        d_row, d_col = -d_col, d_row
    return d_row, d_col


def sensor_offsets(layout: SensorLayout) -> torch.Tensor:
    """Offsets ``[headings=4, sensors, 2]`` int64 of each sensor for each heading."""
    return torch.tensor(
        [[turn_offset(offset, h) for offset in layout.offsets] for h in range(NUM_HEADINGS)],
        dtype=torch.int64,
    )


def draw_permutation(num_sensors: int, seed: int) -> tuple[int, ...]:
    """A uniformly random permutation of ``range(num_sensors)`` from ``seed`` (Fisher-Yates on the
    counter stream ``substream_key_int(seed, SUBSTREAM_PERMUTATION)``, draw ``i`` for position
    ``num_sensors - 1 - i``)."""
    check_int("num_sensors", num_sensors, 1)
    key = substream_key_int(check_int("sensor_permutation", seed, 0), SUBSTREAM_PERMUTATION)
    order = list(range(num_sensors))
    for draw, position in enumerate(range(num_sensors - 1, 0, -1)):
        other = (random_bits_int(key, draw) * (position + 1)) >> 32
        order[position], order[other] = order[other], order[position]
    return tuple(order)


def base_dependency(body: Body, layout: SensorLayout, num_distractors: int) -> torch.Tensor:
    """``[actuators, layout sensors + distractors]`` bool before any permutation: a moving
    actuator's collision is decided by the one sensor looking where it moves (the cross sensor of
    its direction, present in every layout); turns and distractors decide nothing."""
    dependency = torch.zeros(
        body.num_actuators, layout.num_sensors + num_distractors, dtype=torch.bool
    )
    for actuator, move in enumerate(body.moves):
        if move is not None:
            dependency[actuator, layout.directions.index((move,))] = True
    return dependency
