"""The one registry of declared worlds: what ``--world`` names on the command line.

A **declared world** (``DeclaredWorld``) is a Gymnasium env with its ``Declaration``
(``factorq_envs.gymnasium_adapter``) as a command runs it: a function ``seed -> FactorQEnv``, the
observation entry the networks read, the return that counts as learned, and the extras it needs.
The same name reaches it from every command that takes a declared env (``factorq gym --world``,
``factorq risk --worlds``):

- a **built-in** name (``BUILT_IN``: ``highway``, ``minigrid-5x5``, ``minigrid-6x6``,
  ``minigrid-8x8``, ``minigrid-16x16``, the project's own ``grid-10x10``,
  ``grid-10x10-dynamic`` and ``corridor`` through ``factorq_envs.project_worlds``, and
  ``highway-pairs``, highway declaring ``factorq_envs.highway.PAIRED_ORACLE``);
- an **installed** one: a package adds worlds through the ``factorq.worlds`` entry point group,
  each entry point naming a ``DeclaredWorld`` (``[project.entry-points."factorq.worlds"]
  lake = "my_package.worlds:LAKE"``);
- a **user's own**, ``package.module:NAME`` (the module importable from where the command runs),
  naming a ``DeclaredWorld``.

A results file and its kept units hold the name as given, so ``--resume`` and every worker of
a cluster resolve the same world again. A name that does not import, names nothing, names
something other than a ``DeclaredWorld``, or an entry point that raises is one ``WorldError``
line naming it (``resolve_world``), before any work.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
import math
import re
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from factorq_envs.gymnasium_adapter import FactorQEnv

#: The entry point group through which installed packages add worlds.
ENTRY_POINT_GROUP = "factorq.worlds"
_PATH = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")


class WorldError(ValueError):
    """A ``--world`` that names no declared world (one line, naming it)."""


@dataclass(frozen=True)
class DeclaredWorld:
    """A declared Gymnasium world as the commands run it.

    Args:
        make: ``seed -> FactorQEnv``, the world for one experiment (every process resolves the
            world's name again, so nothing here needs to pickle).
        label: its name in reports and figures.
        observation: the observation entry the task networks read (``"observation"`` for a
            non-Dict env's own observation).
        threshold: the default return that counts as learned (``factorq gym``'s "steps to
            threshold").
        requires: ``(module, extra)`` pairs: a module the world imports and the extra that
            installs it, checked before any work.
        exclude: observation entries the torchrl env leaves out (text torchrl cannot batch).
        survival: what counts as a success: an episode that runs to its time limit
            (``truncated``) without a collision (highway), rather than one that ends
            (``terminated``) without one (a goal reached).
        max_steps: the step limit of a greedy episode that a command rolls out itself (the env's
            own time limit, if it has one, ends it sooner).
    """

    make: Callable[[int], FactorQEnv]
    label: str
    observation: str = "observation"
    threshold: float = 0.0
    requires: tuple[tuple[str, str], ...] = ()
    exclude: tuple[str, ...] = ()
    survival: bool = False
    max_steps: int = 1_000

    def __post_init__(self) -> None:
        if not callable(self.make):
            raise TypeError(
                f"DeclaredWorld.make must be callable (seed -> FactorQEnv), got {self.make!r}"
            )
        for name in ("label", "observation"):
            value = getattr(self, name)
            if not isinstance(value, str) or not value:
                raise TypeError(f"DeclaredWorld.{name} must be a non-empty string, got {value!r}")
        threshold = self.threshold
        if isinstance(threshold, bool) or not isinstance(threshold, int | float):
            raise TypeError(f"DeclaredWorld.threshold must be a number, got {threshold!r}")
        if not math.isfinite(threshold):
            raise ValueError(f"DeclaredWorld.threshold={threshold!r} must be finite")
        requires = tuple(tuple(pair) for pair in self.requires)
        if any(len(pair) != 2 or not all(isinstance(p, str) for p in pair) for pair in requires):
            raise TypeError(
                f"DeclaredWorld.requires must be (module, extra) string pairs, "
                f"got {self.requires!r}"
            )
        object.__setattr__(self, "requires", requires)
        object.__setattr__(self, "exclude", tuple(str(entry) for entry in self.exclude))
        if not isinstance(self.survival, bool):
            raise TypeError(f"DeclaredWorld.survival must be a bool, got {self.survival!r}")
        steps = self.max_steps
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"DeclaredWorld.max_steps={steps!r} must be an integer >= 1")

    def step_seconds(self, steps: int = 20) -> float:
        """The median wall time of one step of the world's env (seed 0, after a reset, actions
        drawn from its own action space): what tells a command whether its units are worth
        processes of their own (``factorq_trainers.runner.cluster.default_workers``)."""
        env = self.make(0)
        try:
            env.reset(seed=0)
            env.action_space.seed(0)
            times = []
            for _ in range(steps):
                start = time.perf_counter()
                _, _, terminated, truncated, _ = env.step(env.action_space.sample())
                times.append(time.perf_counter() - start)
                if terminated or truncated:
                    env.reset()
        finally:
            env.close()
        return statistics.median(times)


def make_highway(seed: int) -> FactorQEnv:
    """highway-env's ``highway-fast-v0`` as ``factorq_envs.highway`` declares it."""
    from factorq_envs.highway import make_highway as make

    return make(seed)


def make_highway_paired(seed: int) -> FactorQEnv:
    """``make_highway`` declaring ``factorq_envs.highway.PAIRED_ORACLE``."""
    from factorq_envs.highway import make_highway as make

    return make(seed, paired=True)


def make_minigrid_of(size: int) -> Callable[[int], FactorQEnv]:
    """``seed -> `` MiniGrid Dynamic-Obstacles ``size`` x ``size`` with the "nodeath" semantics
    (the adapter imported when a world is made: listing the worlds imports neither MiniGrid nor
    torch)."""

    def make(seed: int) -> FactorQEnv:
        from factorq_envs.minigrid_adapter import make_minigrid

        return make_minigrid(size, "nodeath", seed=seed)

    return make


def make_project_world(kind: str, period: int = 0) -> Callable[[int], FactorQEnv]:
    """``seed ->`` one of the project's own worlds as a declared world: ``kind`` ``"grid"`` (the
    paper's grid and body, ``WorldConfig()``) or ``"corridor"`` (``CorridorConfig()``), with
    obstacle period ``period``, seen through the adapter like any Gymnasium env
    (``factorq_envs.project_worlds``): the same worlds the other commands step, reachable by
    name from every command that takes a declared world."""

    def make(seed: int) -> FactorQEnv:
        from factorq_envs.project_worlds import declared_project_world

        return declared_project_world(kind, period, seed)

    return make


def _highway_world(make: Callable[[int], FactorQEnv], label: str) -> DeclaredWorld:
    """highway-fast-v0 declared by ``make``: a success survives to the time limit, a training
    return of 20 counts as learned."""
    return DeclaredWorld(
        make, label, threshold=20.0, requires=(("highway_env", "highway"),), survival=True
    )


#: The MiniGrid Dynamic-Obstacles sizes ``factorq minigrid --sizes`` runs, declared as worlds.
MINIGRID_SIZES = (5, 6, 8, 16)


#: The worlds that ship, by name.
BUILT_IN = {
    "highway": _highway_world(make_highway, "highway-fast-v0"),
    **{
        f"minigrid-{size}x{size}": DeclaredWorld(
            make_minigrid_of(size),
            f"MiniGrid-Dynamic-Obstacles-{size}x{size}-v0 (nodeath)",
            observation="image",
            threshold=0.5,
            requires=(("minigrid", "minigrid"),),
            exclude=("mission", "direction"),
        )
        for size in MINIGRID_SIZES
    },
    "grid-10x10": DeclaredWorld(
        make_project_world("grid"), "the paper's grid (10x10, static)", threshold=-36.0
    ),
    "grid-10x10-dynamic": DeclaredWorld(
        make_project_world("grid", 1), "the paper's grid (10x10, dynamic)", threshold=-36.0
    ),
    "corridor": DeclaredWorld(make_project_world("corridor"), "the corridor", threshold=-22.0),
    "highway-pairs": _highway_world(make_highway_paired, "highway-fast-v0 (paired oracle)"),
}


def _installed() -> dict[str, importlib.metadata.EntryPoint]:
    found = importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)
    return {entry.name: entry for entry in found if entry.name not in BUILT_IN}


def names() -> list[str]:
    """The names ``--world`` accepts besides ``package.module:NAME``: built-in, then installed."""
    return [*BUILT_IN, *sorted(_installed())]


def _checked(world: object, what: str) -> DeclaredWorld:
    if not isinstance(world, DeclaredWorld):
        raise WorldError(
            f"{what} names a {type(world).__name__!r} object, not a "
            f"factorq_envs.worlds.DeclaredWorld"
        )
    return world


@functools.cache
def resolve_world(name: str) -> DeclaredWorld:
    """The declared world ``name`` names (module docstring), else one ``WorldError`` line.

    Args:
        name: a built-in name, an installed entry point's name, or ``package.module:NAME``.
    """
    if not isinstance(name, str):
        raise WorldError(f"world={name!r} must be a name (text)")
    if name in BUILT_IN:
        return BUILT_IN[name]
    if ":" in name:
        if not _PATH.match(name):
            raise WorldError(f"world {name!r} is not package.module:NAME")
        module_name, attribute = name.split(":")
        try:
            module = importlib.import_module(module_name)
        except Exception as error:  # noqa: BLE001 - the user's module: one line, whatever it raised
            raise WorldError(
                f"world {name!r}: module {module_name!r} does not import "
                f"({type(error).__name__}: {error})"
            ) from None
        if not hasattr(module, attribute):
            raise WorldError(f"world {name!r}: module {module_name!r} has no {attribute!r}")
        return _checked(getattr(module, attribute), f"world {name!r}")
    installed = _installed()
    if name in installed:
        entry = installed[name]
        try:
            loaded = entry.load()
        except Exception as error:  # noqa: BLE001 - an installed package's code: one line
            raise WorldError(
                f"world {name!r}: entry point {entry.value!r} of {ENTRY_POINT_GROUP} raised "
                f"{type(error).__name__}: {error}"
            ) from None
        return _checked(loaded, f"world {name!r} (entry point {entry.value!r})")
    raise WorldError(
        f"world {name!r} is unknown: choose one of {', '.join(names())}, or name your own "
        f"declared world as package.module:NAME"
    )
