"""Hyperparameters of the tabular agents (SPEC section 3), validated where they enter."""

from __future__ import annotations

import math
from dataclasses import dataclass

ALGORITHMS = ("q-learning", "factor-q")


def _check_float(name: str, value, low: float, high: float, *, low_open=False, high_open=False):
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise TypeError(f"{name} must be a number, got {value!r} ({type(value).__name__})")
    below = value <= low if low_open else value < low
    above = value >= high if high_open else value > high
    if not math.isfinite(value) or below or above:
        interval = f"{'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise ValueError(f"{name}={value} is out of range: must be in {interval}")


@dataclass(frozen=True)
class AgentConfig:
    """Learning parameters shared by Q-learning and Factor-Q (defaults: the paper's)."""

    epsilon: float = 0.01
    """Probability of a uniformly random (exploratory) action."""
    gamma: float = 0.9
    """Discount of future reward."""
    alpha: float = 0.2
    """Task learning rate (eqs. 1 and 4)."""
    eta: float = 0.1
    """Margin by which the scaled local reward dominates the task reward (eq. 3)."""
    g_min: float = 0.01
    """Floor of the normaliser G (eq. 3), so local reward decides in unvisited states."""

    def __post_init__(self) -> None:
        _check_float("epsilon", self.epsilon, 0.0, 1.0)
        _check_float("gamma", self.gamma, 0.0, 1.0, high_open=True)
        _check_float("alpha", self.alpha, 0.0, 1.0, low_open=True)
        _check_float("eta", self.eta, 0.0, 1e6)
        _check_float("g_min", self.g_min, 0.0, 1e6, low_open=True)


def check_algorithm(algorithm: str) -> str:
    """Return ``algorithm`` if it is one of ``ALGORITHMS``, else raise a ValueError naming them."""
    if algorithm not in ALGORITHMS:
        raise ValueError(
            f"algorithm={algorithm!r} is unknown: choose one of {', '.join(ALGORITHMS)}"
        )
    return algorithm
