"""``factorq risk``'s configuration: ``RiskConfig`` (one budget and DQN recipe for every
method), the worlds and methods it runs. The command is ``factorq_trainers.commands.risk.command``;
the methods are ``factorq_trainers.commands.risk.methods``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from factorq_torch.base.validation import check_float, check_int, check_names
from factorq_trainers.analysis.vocabulary import among
from factorq_trainers.runner.options import option

Progress = Callable[[int], None]
#: The worlds that are the project's own torchrl envs (sized by grid_size, minigrid_size); any
#: other name is a declared world of ``factorq_envs.worlds``' registry (highway, an installed
#: one, or package.module:NAME).
OWN_WORLDS = ("grid", "minigrid")
METHODS = among("dqn", "dqn+risk", "dqn+risk-learned", "sb3-dqn", "sb3-dqn+risk")
TORCHRL_METHODS = METHODS[:3]
#: The worlds the sb3-* methods can run on (``risk_methods.run_sb3``: the gymnasium grid).
SB3_WORLDS = ("grid",)


def _worlds(value: Any) -> tuple[str, ...]:
    """``worlds``: the own worlds and declared ones (``factorq_envs.worlds``), each declared
    world resolved now (one line naming the field and the world)."""
    from factorq_envs.worlds import WorldError, names, resolve_world

    given = [name.strip() for name in value.split(",")] if isinstance(value, str) else value
    worlds = tuple(name for name in given if name != "")
    declared = tuple(name for name in names() if name not in OWN_WORLDS)
    choices = f"{', '.join((*OWN_WORLDS, *declared))}, or your own as package.module:NAME"
    if not worlds:
        raise ValueError(f"worlds is empty: choose one or more of {choices}")
    for name in worlds:
        if name not in OWN_WORLDS and ":" not in name and name not in declared:
            raise ValueError(f"worlds: {name!r} is unknown: choose from {choices}")
        if name not in OWN_WORLDS:
            try:
                resolve_world(name)
            except WorldError as error:
                raise WorldError(f"worlds: {error}") from None
    return worlds


@dataclass(frozen=True)
class RiskConfig:
    """One budget and DQN recipe for every method (``factorq_trainers.commands.risk.command``'s
    docstring); each option's help says what it sets."""

    worlds: tuple[str, ...] = option(
        ("grid", "minigrid"),
        "Worlds: grid, minigrid, and declared worlds: highway (highway-fast-v0: ask for it), one "
        "an installed package adds (entry point group factorq.worlds), or your own as "
        "package.module:NAME (a factorq_envs.worlds.DeclaredWorld).",
    )
    methods: tuple[str, ...] = option(TORCHRL_METHODS, f"Methods, of {', '.join(METHODS)}.")
    sb3_worlds: tuple[str, ...] = option(SB3_WORLDS, "Worlds the sb3-* methods run on: grid.")
    seeds: int = option(3, "Seeds per (world, method).")
    seed: int = option(0, "First seed.")
    steps: int = option(3000, "Env steps of training per unit.")
    grid_size: int = option(6, "Side of the dynamic grid.")
    grid_obstacles: int = option(6, "Obstacles of the dynamic grid (they move every step).")
    minigrid_size: int = option(8, "Side of MiniGrid Dynamic-Obstacles.")
    hidden: int = option(64, "Width of the two hidden layers of the Q-network.")
    lr: float = option(1e-3, "Adam learning rate.")
    gamma: float = option(0.9, "Discount.")
    buffer_size: int = option(10_000, "Replay buffer capacity (transitions).")
    batch_size: int = option(64, "Minibatch size.")
    learning_starts: int = option(200, "Env steps before the first gradient step.")
    train_every: int = option(2, "Env steps per gradient step.")
    tau: float = option(0.02, "SoftUpdate's rate (target <- (1 - tau) target + tau net).")
    eps_start: float = option(1.0, "Initial epsilon.")
    eps_end: float = option(0.05, "Final epsilon.")
    exploration_fraction: float = option(0.3, "Fraction of the steps epsilon anneals over.")
    eval_episodes: int = option(10, "Greedy episodes after training.")
    success_threshold: float = option(0.8, "Success rate of 10 episodes that counts as learned.")
    out: str = option("results/risk", "Directory for the json, figure and report.")

    def __post_init__(self) -> None:
        object.__setattr__(self, "worlds", _worlds(self.worlds))
        object.__setattr__(self, "methods", check_names("methods", self.methods, METHODS))
        object.__setattr__(
            self, "sb3_worlds", check_names("sb3_worlds", self.sb3_worlds, SB3_WORLDS)
        )
        for name in ("seeds", "steps", "hidden", "buffer_size", "batch_size", "train_every"):
            check_int(name, getattr(self, name), 1)
        for name in ("seed", "learning_starts", "eval_episodes"):
            check_int(name, getattr(self, name), 0)
        check_int("grid_size", self.grid_size, 3)
        check_int("minigrid_size", self.minigrid_size, 5)
        for name in ("lr", "gamma", "tau", "eps_start", "eps_end", "exploration_fraction"):
            check_float(name, getattr(self, name), 0.0, 1.0)
        check_float("success_threshold", self.success_threshold, 0.0, 1.0)
        if self.eps_end > self.eps_start:
            raise ValueError(f"eps_end={self.eps_end} must be <= eps_start={self.eps_start}")
