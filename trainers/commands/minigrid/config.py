"""``factorq minigrid``'s configuration: ``MiniGridConfig``, the methods and their labels, the
sizes, collision semantics and sensor layouts it runs. The command is
``factorq_trainers.commands.minigrid.command``; the methods are
``factorq_trainers.commands.minigrid.methods``.
"""

from __future__ import annotations

from dataclasses import dataclass

from factorq_torch.base.config import EXPLORATIONS
from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_trainers.analysis.vocabulary import among
from factorq_trainers.runner.options import check_choices, option

METHODS = among(
    "factor-q-learned",
    "factor-q-posterior",
    "factor-q",
    "q-learning",
    "dqn",
    "dqn-image",
)
#: factor-q-posterior (StructureLearner's own open prediction) is an ablation, run on request.
DEFAULT_METHODS = tuple(m for m in METHODS if m != "factor-q-posterior")
SIZE_NAMES = ("5", "6", "8", "16")
SEMANTICS_NAMES = ("minigrid", "nodeath")
LAYOUT_NAMES = ("front3", "ahead6")
SUCCESS_THRESHOLD = 0.9


@dataclass(frozen=True)
class MiniGridConfig:
    """The MiniGrid experiment (each option's help says what it sets); the defaults run in a
    few minutes on 2 cores (``docs/tutorials/minigrid.md``)."""

    seed: int = option(0, "Master seed: worlds, policies and networks derive from it.")
    seeds: int = option(10, "Independent experiments per size and method.")
    sizes: tuple[str, ...] = option(SIZE_NAMES, "Sizes to run: 5, 6, 8, 16 (comma-separated).")
    methods: tuple[str, ...] = option(
        DEFAULT_METHODS,
        "Methods to run (comma-separated): " + ", ".join(METHODS) + ".",
    )
    steps: int = option(
        1_000, "Env steps per seed at 5x5; size n gets steps * n / 5, the same for every method."
    )
    semantics: str = option(
        "minigrid",
        "Collision semantics: minigrid (a collision ends the episode) or nodeath (it goes on).",
        choices=SEMANTICS_NAMES,
    )
    layout: str = option(
        "front3",
        "Sensors read from the view: front3 or ahead6 (factorq_envs.minigrid_adapter).",
        choices=LAYOUT_NAMES,
    )
    exploration: str = option(
        "uniform",
        "Tabular Factor-Q's exploratory actions: uniform (the paper) or risk-aware (uniform among "
        "the actuators its local model does not call risky, rho_a >= -0.5). Q-learning and DQN "
        "explore uniformly.",
        choices=EXPLORATIONS,
    )
    window: int = option(10, "Finished episodes in the success rate behind 'steps to 90%'.")
    final_fraction: float = option(
        0.2, "Fraction of the budget, at its end, whose episodes give the final measures."
    )
    out: str = option("results/minigrid", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        check_int("seed", self.seed, 0, 2**31 - 1)
        check_int("seeds", self.seeds, 1, 10_000)
        object.__setattr__(self, "sizes", check_names("sizes", self.sizes, SIZE_NAMES))
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        check_int("steps", self.steps, 10, 10**8)
        check_choices(self)  # semantics, layout, exploration
        check_int("window", self.window, 1, 10_000)
        check_float("final_fraction", self.final_fraction, 0.0, 1.0, low_open=True)

    def budget(self, size: int) -> int:
        """Env steps per seed at ``size``."""
        return max(1, round(self.steps * size / 5))
