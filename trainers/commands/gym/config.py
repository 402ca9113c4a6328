"""``factorq gym``'s configuration: ``GymConfig`` and its methods; the declared worlds it runs
are ``factorq_envs.worlds``' registry (``--world``). The command is
``factorq_trainers.commands.gym.command``; the methods are
``factorq_trainers.commands.gym.methods``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

from factorq_torch.base.config import EXPLORATIONS, check_exploration
from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_trainers.analysis.vocabulary import among
from factorq_trainers.runner.options import option

if TYPE_CHECKING:
    from factorq_envs.worlds import DeclaredWorld

METHODS = among("dqn", "factor-dqn", "factor-dqn-learned", "sb3-dqn")
DEFAULT_METHODS = ("dqn", "factor-dqn", "factor-dqn-learned")


@dataclass(frozen=True)
class GymConfig:
    """The experiment; the defaults' cost on highway (about 6 min of wall time on 2 idle cores):
    ``docs/tutorials/highway.md``."""

    world: str = option(
        "highway",
        "The declared world: highway, minigrid-5x5 (6x6, 8x8, 16x16), a world an installed "
        "package adds (entry point group factorq.worlds), or your own as package.module:NAME (a "
        "factorq_envs.worlds.DeclaredWorld).",
    )
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
        self.spec  # noqa: B018 - resolved (imported) now: a bad --world is refused before any work
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
    def spec(self) -> DeclaredWorld:
        """The declared world ``world`` names (``factorq_envs.worlds.resolve_world``)."""
        from factorq_envs.worlds import resolve_world

        return resolve_world(self.world)

    @property
    def return_threshold(self) -> float:
        """``threshold``, else the world's default."""
        return self.spec.threshold if self.threshold is None else self.threshold
