"""The tiny configurations of ``tests/test_command_figures.py`` and the exact part of their
results; ``python tests/command_figures.py`` rewrites ``tests/data/command_figures.json`` (only
when a change of numbers is intended: say why in docs/decisions.md)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from factorq_trainers.runner.results import dumps

DATA = Path(__file__).parent / "data" / "command_figures.json"
#: Tabular methods only: their numbers are integer counts and table arithmetic (bit-exact on any
#: CPU); the networks' (dqn, factor-dqn, dqn-image) are checked for structure only.
COMPARE = {"seeds": 2, "steps": 400, "methods": ["factor-q", "q-learning"], "threads": 1}
DEPENDENCIES = {
    "seeds": 3,
    "runs": 4,
    "episodes": 1,
    "change_run": 2,
    "settings": ["cross", "noise-5", "change"],
    "threads": 1,
}
MINIGRID = {
    "seeds": 2,
    "sizes": ["5"],
    "steps": 60,
    "methods": ["factor-q-learned", "factor-q", "q-learning"],
}


#: Left out at any depth: wall times, and the intervals (their method is the statistics'
#: module's to change; the numbers they are drawn around stay exact).
INTERVALS = ("ci", "low", "high")


def _drop(tree: Any, names: tuple[str, ...]) -> Any:
    """``tree`` without the entries named ``names``, ``INTERVALS`` or ``*ci95`` at any depth."""
    if isinstance(tree, dict):
        return {
            k: _drop(v, names)
            for k, v in tree.items()
            if k not in names and k not in INTERVALS and not k.endswith("ci95")
        }
    if isinstance(tree, list):
        return [_drop(v, names) for v in tree]
    return tree


def compare_exact(results: dict[str, Any]) -> dict[str, Any]:
    return _drop({"results": results["results"], "curves": results["curves"]}, ("wall_s",))


#: ``dependencies``' absolute task measures (issue 39), derived from the steps and returns the
#: stored digest already covers: left out, so the digest stored before them still checks.
DEPENDENCIES_DERIVED = ("steps_per_episode", "fraction_truncated", "absolute")


def dependencies_exact(results: dict[str, Any]) -> dict[str, Any]:
    exact = {"settings": results["settings"], "skipped": results["skipped"]}
    return _drop(exact, DEPENDENCIES_DERIVED)


def minigrid_exact(results: dict[str, Any]) -> dict[str, Any]:
    return _drop({"results": results["results"]}, ("wall_s",))


def digest(exact: dict[str, Any]) -> str:
    return hashlib.sha256(dumps(exact).encode()).hexdigest()


def compute() -> dict[str, Any]:
    import os

    from factorq_trainers.commands.compare import command as compare
    from factorq_trainers.commands.dependencies import command as dependencies
    from factorq_trainers.commands.minigrid import command as minigrid

    stored: dict[str, Any] = {}
    with_out = {"out": os.devnull}
    exact = compare_exact(compare.run(compare.CompareConfig(**COMPARE, **with_out)))
    stored["compare"] = {"config": COMPARE, "sha256": digest(exact), "exact": exact}
    config = dependencies.DependenciesConfig(**DEPENDENCIES, **with_out)
    exact = dependencies_exact(dependencies.run(config))
    stored["dependencies"] = {"config": DEPENDENCIES, "sha256": digest(exact), "exact": exact}
    exact = minigrid_exact(minigrid.run(minigrid.MiniGridConfig(**MINIGRID, **with_out)))
    stored["minigrid"] = {"config": MINIGRID, "sha256": digest(exact), "exact": exact}
    return stored


if __name__ == "__main__":
    DATA.write_text(dumps(compute()))
    print(DATA)
