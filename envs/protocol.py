"""The World protocol: what a world offers the env wrappers, the experiments and the fast path.

A world is pure batched functions over a state of tensors with a leading dimension ``S`` of
independent worlds, plus the data that describes its body (``dependency``). ``factorq_envs.world``'s
``FactoredGrid`` implements it for the paper's grid; a new world is one new file with a class
like it (and, for the compiled path, a kernel loop). Nothing here imports a world.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Protocol, runtime_checkable

import torch


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
        """Start new episodes where ``mask`` ``[S]`` is True."""

    def step(
        self, state: NamedTuple, action: torch.Tensor, key: torch.Tensor, period: torch.Tensor
    ) -> tuple[NamedTuple, NamedTuple]:
        """One action per world: ``(new state, outcome)`` (rewards, collision vector, flags)."""

    def observe(self, state: NamedTuple, key: torch.Tensor) -> torch.Tensor:
        """All sensors as the agent receives them, ``[S, K]`` bool."""

    def render(self, state: NamedTuple, index: int = 0) -> str:
        """A text picture of world ``index``."""
