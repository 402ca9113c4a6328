"""Pictures of one FactoredGrid world as RGB arrays (``render_mode="rgb_array"``, the ``pixels``
of ``factorq_envs.transforms.RenderPixels``): numpy only, no drawing library.

Drawn on a square of ``(size + 2) * scale`` pixels: the wall around the grid (grey), obstacles
(near black), the goal (green), the agent (blue) with a white mark on the side it faces (bodies
with a heading), and the last collision as a red bar on the face that bumped. ``mark_risk`` adds
the local-risk layer's explanations (``factorq_torch.risk``): an orange mark on the side of every
actuator the layer penalises, deeper for a larger penalty.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from factorq_envs.body import Body

#: Pixels per cell (a 10x10 grid with its wall: 192 x 192, divisible by 16 as video codecs like).
SCALE = 16
FLOOR = (235, 235, 235)
WALL = (110, 110, 110)
OBSTACLE = (35, 35, 35)
GOAL = (60, 170, 75)
AGENT = (40, 90, 220)
MARK = (255, 255, 255)
COLLISION = (220, 40, 40)
RISK = (245, 150, 20)
#: (d_row, d_col) of the four directions: 0 north, 1 west, 2 south, 3 east.
OFFSETS = ((-1, 0), (0, -1), (1, 0), (0, 1))


def bumped_faces(bump: Sequence[bool] | torch.Tensor, heading: int, body: Body) -> list[int]:
    """The absolute directions (0 N, 1 W, 2 S, 3 E) of the actuators that bumped last step."""
    faces = []
    for actuator, hit in enumerate(bump):
        move = body.moves[actuator]
        if hit and move is not None:
            faces.append((move + heading) % len(OFFSETS))
    return faces


def risky_faces(
    penalties: Sequence[float] | torch.Tensor, heading: int, body: Body, threshold: float = 0.05
) -> list[tuple[int, float]]:
    """``(face, penalty)`` of every moving actuator whose penalty (``G rho_a``, ``[A]``) is below
    ``-threshold``: the absolute direction it would move in (as ``bumped_faces``)."""
    faces = []
    for actuator, penalty in enumerate(penalties):
        move = body.moves[actuator]
        if float(penalty) < -threshold and move is not None:
            faces.append(((move + heading) % len(OFFSETS), float(penalty)))
    return faces


def mark_risk(
    image: np.ndarray,
    cell: int,
    size: int,
    faces: Sequence[tuple[int, float]],
    *,
    scale: int = SCALE,
) -> np.ndarray:
    """``image`` (a ``render_rgb`` frame, changed in place and returned) with an orange mark in
    the agent's cell next to each face of ``faces`` (``risky_faces``): a bar whose depth grows
    with the penalty, from an eighth of the cell (small) to a third (a penalty of 1 or more).

    >>> frame = render_rgb(0, torch.zeros(4, dtype=torch.bool), 2, scale=8)
    >>> mark_risk(frame, 0, 2, [(3, -1.0)], scale=8)[12, 15].tolist()  # east side of the agent
    [245, 150, 20]
    """
    row, col = divmod(int(cell), size)
    top, left = (row + 1) * scale, (col + 1) * scale
    for face, penalty in faces:
        depth = max(1, round(scale * min(1.0, max(0.375, abs(penalty))) / 3))
        d_row, d_col = OFFSETS[face]
        if d_row:
            edge = top if d_row < 0 else top + scale - depth
            image[edge : edge + depth, left + depth : left + scale - depth] = RISK
        else:
            edge = left if d_col < 0 else left + scale - depth
            image[top + depth : top + scale - depth, edge : edge + depth] = RISK
    return image


def render_rgb(
    cell: int,
    obstacles: torch.Tensor | np.ndarray,
    size: int,
    *,
    heading: int | None = None,
    bumped: tuple[int, ...] | list[int] = (),
    scale: int = SCALE,
) -> np.ndarray:
    """One world as ``uint8 [(size + 2) * scale, (size + 2) * scale, 3]``.

    Args:
        cell: the agent's cell, ``row * size + col``.
        obstacles: bool ``[size * size]``.
        size: the grid's side.
        heading: the direction faced (0 N, 1 W, 2 S, 3 E), marked; ``None``: no mark.
        bumped: the faces that hit something on the last action (``bumped_faces``).
        scale: pixels per cell.

    >>> frame = render_rgb(0, torch.zeros(4, dtype=torch.bool), 2, bumped=[0], scale=4)
    >>> frame.shape, frame.dtype, frame[0, 0].tolist(), frame[5, 6].tolist()  # wall, agent
    ((16, 16, 3), dtype('uint8'), [110, 110, 110], [40, 90, 220])
    """
    side = (size + 2) * scale
    image = np.empty((side, side, 3), dtype=np.uint8)
    image[:] = WALL

    def fill(row: int, col: int, colour: Sequence[int], inset: int = 0) -> None:
        top, left = (row + 1) * scale + inset, (col + 1) * scale + inset
        image[top : top + scale - 2 * inset, left : left + scale - 2 * inset] = colour

    blocked = np.asarray(obstacles, dtype=bool).reshape(size, size)
    for row in range(size):
        for col in range(size):
            fill(row, col, OBSTACLE if blocked[row, col] else FLOOR)
    fill(size - 1, size - 1, GOAL)
    row, col = divmod(int(cell), size)
    inset = max(1, scale // 8)
    fill(row, col, AGENT, inset)
    top, left = (row + 1) * scale, (col + 1) * scale
    middle, third = scale // 2, max(1, scale // 3)
    if heading is not None:  # a white square between the centre and the side faced
        d_row, d_col = OFFSETS[heading % len(OFFSETS)]
        centre_row, centre_col = top + middle + d_row * third, left + middle + d_col * third
        half = max(1, scale // 8)
        image[centre_row - half : centre_row + half, centre_col - half : centre_col + half] = MARK
    bar = max(1, scale // 8)
    for face in bumped:  # a red bar along the face that hit something
        d_row, d_col = OFFSETS[face]
        if d_row:
            edge = top if d_row < 0 else top + scale - bar
            image[edge : edge + bar, left : left + scale] = COLLISION
        else:
            edge = left if d_col < 0 else left + scale - bar
            image[top : top + scale, edge : edge + bar] = COLLISION
    return image
