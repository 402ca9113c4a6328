"""``factorq gym``'s configuration: ``GymConfig``, its methods and the declared worlds it runs
(``WORLDS``). The command is ``factorq_trainers.experiments.gym``, which re-exports these names;
the methods are ``factorq_trainers.experiments.gym_methods``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from factorq_torch.base.config import EXPLORATIONS, check_exploration
from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_trainers.runner.options import option

if TYPE_CHECKING:
    from factorq_envs.gymnasium_adapter import FactorQEnv

METHODS = ("dqn", "factor-q-oracle", "factor-q-learned", "sb3-dqn")
DEFAULT_METHODS = ("dqn", "factor-q-oracle", "factor-q-learned")


@dataclass(frozen=True)
class WorldSpec:
    """A declared world as the experiment runs it."""

    make: str  # "module:function", seed -> FactorQEnv
    observation: str  # the entry the networks read
    threshold: float  # the default return threshold
    extra: str  # what prepare() imports
    label: str


WORLDS = {
    "highway": WorldSpec(
        "factorq_envs.highway:make_highway",
        "observation",
        20.0,
        "highway",
        "highway-fast-v0",
    ),
    "minigrid-8x8": WorldSpec(
        f"{__name__}:make_minigrid_8x8",  # this module, wherever the runner puts it
        "image",
        0.5,
        "minigrid",
        "MiniGrid-Dynamic-Obstacles-8x8-v0 (nodeath)",
    ),
}


def make_minigrid_8x8(seed: int) -> FactorQEnv:
    """MiniGrid Dynamic-Obstacles 8x8 with the "nodeath" semantics (``WORLDS["minigrid-8x8"]``).

    Args:
        seed: the env seed.
    """
    from factorq_envs.minigrid_adapter import make_minigrid

    return make_minigrid(8, "nodeath", seed=seed)


@dataclass(frozen=True)
class GymConfig:
    """The experiment. The defaults (3 seeds x 1,000 steps x 3 methods: at most 10,350 env
    steps with the greedy episodes) took about 75 s of CPU time per unit on highway (about 11 min
    of CPU in all, about 6 min of wall time on 2 idle cores as two processes; with ``sb3-dqn`` 938 s
    of CPU for the 12 units: ``docs/tutorials/highway.md``)."""

    world: str = option("highway", "The declared world.", choices=tuple(WORLDS))
    seed: int = option(0, "Master seed: env seeds, policies and networks derive from it.")
    seeds: int = option(3, "Independent experiments per method.")
    methods: tuple[str, ...] = option(
        DEFAULT_METHODS, "Methods (comma-separated): " + ", ".join(METHODS) + "."
    )
    steps: int = option(1_000, "Training env steps per experiment, the same for every method.")
    eval_episodes: int = option(5, "Greedy episodes after training.")
    window: int = option(5, "Finished episodes in the mean return of the curves and threshold.")
    threshold: float | None = option(
        None, "Return threshold for 'steps to threshold' (default: the world's)."
    )
    exploration: str = option(
        "uniform",
        "Neural Factor-Q's exploratory actions: uniform or risk-aware (uniform among the actuators "
        "its local model does not call risky: rho_a below minus half the declared collision "
        "penalty). DQN and SB3's DQN explore uniformly.",
        choices=EXPLORATIONS,
    )
    curve_points: int = option(20, "Points of the curves in the figure.")
    out: str = option("results/gym", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        if self.world not in WORLDS:
            raise ValueError(f"world={self.world!r}: choose one of {', '.join(WORLDS)}")
        check_int("seed", self.seed, 0, 2**31 - 1)
        check_int("seeds", self.seeds, 1, 1_000)
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("steps", self.steps, 10, 10**8)
        check_int("eval_episodes", self.eval_episodes, 1, 10_000)
        check_int("window", self.window, 1, 10_000)
        if self.threshold is not None:
            check_float("threshold", self.threshold, -math.inf, math.inf)
        check_int("curve_points", self.curve_points, 1, 1_000)
        check_exploration(self.exploration)

    @property
    def spec(self) -> WorldSpec:
        """The declared world (``WORLDS[world]``)."""
        return WORLDS[self.world]

    @property
    def return_threshold(self) -> float:
        """``threshold``, else the world's default."""
        return self.spec.threshold if self.threshold is None else self.threshold
