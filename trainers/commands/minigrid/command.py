"""Factor-Q on MiniGrid Dynamic-Obstacles against Q-learning and DQN: ``factorq minigrid``, a
command module of the runner; ``MiniGridConfig`` and its names in ``config.py``, the methods in
``methods.py``, the Markdown and figure in ``report.py``. The methods, the measures and the
defaults' run: ``docs/tutorials/minigrid.md``.

One unit per size and method, all ``seeds`` of a method in one batch, every method on the same
env-step budget (``steps * size / 5``) and worlds: ``factor-q-learned`` (``StructureLearner``,
told only ``A = 3`` and ``K``), ``factor-q-posterior`` (its own open prediction, an ablation),
``factor-q`` (``LocalRewardTable`` on forward <- front), ``q-learning`` (cell, heading, all
sensors), ``dqn`` (``methods.dqn`` on the same information) and ``dqn-image`` (MiniGrid's 7x7x3
``image``). The tabular agents run on the modular torchrl path: the compiled kernel cannot step
MiniGrid.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from factorq_trainers.analysis.stats import DESCRIPTION as DESCRIPTION_OF_STATISTICS
from factorq_trainers.analysis.vocabulary import label
from factorq_trainers.commands.minigrid.config import METHODS, MiniGridConfig
from factorq_trainers.commands.minigrid.methods import RUNNERS
from factorq_trainers.commands.minigrid.report import FOUND_TARGET_STEPS
from factorq_trainers.methods.units import seed_stat, torch_threads
from factorq_trainers.runner import frame, resources
from factorq_trainers.runner.kept import COUNT, FRACTION, NON_NEGATIVE, NUMBER

NAME = "minigrid"
HELP = (
    "Factor-Q against Q-learning and DQN on MiniGrid Dynamic-Obstacles (needs the minigrid extra)"
)
EXTRA = "factorq-torch[minigrid]"
DESCRIPTION = (
    "Train Factor-Q (learned dependencies and oracle pairing), Q-learning and DQN (same "
    "information, and MiniGrid's image) on MiniGrid-Dynamic-Obstacles-{5x5,6x6,8x8,16x16}-v0 with "
    "equal env-step budgets; write minigrid.json, minigrid.png and minigrid.md to --out. Needs "
    f"pip install '{EXTRA}'."
)
HINT = "use fewer --seeds or --steps, or smaller --sizes"
WORK_UNIT = "step"
NOTICE = (
    "factorq minigrid: the tabular agents run on the modular torchrl path (the compiled kernel "
    "cannot step MiniGrid)"
)


CONFIG = MiniGridConfig

#: The per-seed measures ``summarise_method`` summarises (means over seeds, 95% intervals).
MEASURES = (
    "success_rate",
    "return",
    "steps_to_goal",
    "collisions",
    "greedy_collisions",
    "steps_to_90",
    "episodes",
)
_STAT = {"mean": NUMBER, "ci95": (None, [NUMBER]), "n": COUNT}
#: A unit's result (``run_unit``), what a kept one must hold (``runner.kept``'s schema).
UNIT_RESULT = {
    "seeds": {
        "success_rate": [FRACTION],
        "return": [NUMBER],
        "steps_to_goal": [NON_NEGATIVE],
        "episodes": [COUNT],
        "steps_to_90": [(None, COUNT)],
        "collisions": [COUNT],
        "greedy_collisions": [COUNT],
        "wall_s": NON_NEGATIVE,
        "found_forward_front?": [(None, COUNT)],
        "structure_at_end?": [[[COUNT]]],
    },
    "summary": {
        **dict.fromkeys(MEASURES, _STAT),
        "found_forward_front?": _STAT,
        "found_within_target?": FRACTION,
        "found_at_all?": FRACTION,
        "wall_s": NON_NEGATIVE,
        "env_steps_per_seed": COUNT,
    },
}


# --------------------------------------------------------------------------------------------
# The experiment


def summarise_method(result: dict[str, Any], budget: int, seed: int = 0) -> dict[str, Any]:
    """Each measure's mean over seeds and 95% interval (Wilson for the success rate, the BCa
    bootstrap otherwise), and how often the learner found forward <- front.

    Args:
        result: a method's per-seed measures (``methods.summary`` and ``wall_s``).
        budget: the env steps each seed ran.
        seed: the master seed (the bootstrap's resamples).
    """
    summary: dict[str, Any] = {
        name: seed_stat(result[name], seed, name == "success_rate") for name in MEASURES
    }
    found = result.get("found_forward_front")
    if found is not None:
        within = [f is not None and f <= FOUND_TARGET_STEPS for f in found]
        summary["found_forward_front"] = seed_stat(found, seed)
        summary["found_within_target"] = float(np.mean(within))
        summary["found_at_all"] = float(np.mean([f is not None for f in found]))
    return {**summary, "wall_s": result["wall_s"], "env_steps_per_seed": budget}


def estimate(config: MiniGridConfig) -> resources.Estimate:
    """Peak memory: each method's per-episode records hold a slot per env step of the budget
    (an episode lasts at least one), and Q-learning's table is ``[S, cells * headings * 2**K,
    A]`` at the largest size, for the body of ``config``'s sensor layout."""
    from factorq_envs.body import HEADING
    from factorq_envs.minigrid_adapter import sensor_names

    sensors, headings = len(sensor_names(config.layout)), HEADING.num_headings
    budget = max(config.budget(int(size)) for size in config.sizes)
    cells = max(int(size) ** 2 for size in config.sizes)
    records = 3 * config.seeds * budget * resources.METRIC_BYTES
    tables = config.seeds * cells * headings * (1 << sensors) * len(HEADING.actuators) * 4
    parts = {"episode records": records, "tables": tables}
    return resources.Estimate(parts, budget * config.seeds * len(config.methods), exact_steps=True)


def units(config: MiniGridConfig) -> list[dict[str, Any]]:
    """One unit per size and method (a method's seeds run as one batch)."""
    return [
        {"id": f"{size}/{method}", "size": int(size), "method": method}
        for size in config.sizes
        for method in config.methods
    ]


def work(config: MiniGridConfig, unit: dict[str, Any]) -> int:
    """A unit's env steps per seed (what ``run_unit`` reports to ``progress``)."""
    return config.budget(unit["size"])


def prepare(config: MiniGridConfig) -> None:
    """The minigrid extra installed, else ``require_minigrid``'s ModuleNotFoundError."""
    from factorq_envs.minigrid_adapter import require_minigrid

    require_minigrid()


def run_unit(
    config: MiniGridConfig, unit: dict[str, Any], progress: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """One method at one size, all seeds; ``progress(env_steps)`` after each 100 steps."""
    size, method = unit["size"], unit["method"]
    with torch_threads(1):
        raw = RUNNERS[method](config, size, method, progress or (lambda steps: None))
    return {"seeds": raw, "summary": summarise_method(raw, config.budget(size), config.seed)}


def summarise(config: MiniGridConfig, outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    """``minigrid.json``'s entries from the units (in ``units`` order)."""
    from factorq_envs.minigrid_adapter import sensor_names

    results: dict[str, Any] = {}
    for unit, outcome in zip(units(config), outcomes, strict=True):
        results.setdefault(str(unit["size"]), {})[unit["method"]] = outcome
    return {
        "sensors": list(sensor_names(config.layout)),
        "budgets": {size: config.budget(int(size)) for size in config.sizes},
        "results": results,
        "statistics": DESCRIPTION_OF_STATISTICS,
        "notice": NOTICE,
        "methods": {method: label(method) for method in METHODS},
    }


def run(config: MiniGridConfig, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Every method on every size, here; the results (what ``minigrid.json`` holds)."""
    return frame.run_in_process(sys.modules[__name__], config, progress)
