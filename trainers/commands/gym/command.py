"""Factor-Q on a declared Gymnasium world against DQN: ``factorq gym``, a command module of the
runner (``factorq_trainers.runner.frame``); ``GymConfig`` in ``config.py``, the methods in
``methods.py``, the Markdown and figure in ``report.py``. The experiment and a run on highway:
``docs/tutorials/highway.md``.

One unit per ``(method, seed)``, every method on the same env-step budget and env seeds (common
random numbers): ``dqn`` (``factorq_trainers.methods.dqn``'s torchrl DQN with highway-env's
documented SB3 settings, ``HIGHWAY_DQN``), ``factor-dqn`` (neural Factor-Q: a task network on the
same observation trained online by ``FactorQLoss``, ``LocalRewardTable`` on the declared oracle
and the binary sensors, eq. 5), ``factor-dqn-learned`` (``StructureLearner(prediction=
"committed")`` told only ``A`` and ``K``) and ``sb3-dqn`` (Stable-Baselines3's DQN, the ``sb3``
extra). Measures: training crashes per 1,000 env steps, the greedy crash rate and return after
training (fresh env seeds), env steps until the mean return of the last ``window`` episodes
reaches ``threshold``, env steps per second, and curves; intervals over seeds: Wilson's for the
greedy crash rate, the BCa bootstrap of the mean otherwise.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

from factorq_trainers.analysis.stats import seed_bands
from factorq_trainers.commands.gym.config import GymConfig
from factorq_trainers.commands.gym.methods import RUNNERS
from factorq_trainers.methods.units import require_extras, seed_stat, torch_threads, world_processes
from factorq_trainers.runner import frame
from factorq_trainers.runner.kept import COUNT, FLAG, NON_NEGATIVE, NUMBER, TEXT

NAME = "gym"
WORK_UNIT = "step"
HELP = (
    "Factor-Q (oracle and learned dependencies) against DQN on a declared Gymnasium world "
    "(highway-fast-v0, MiniGrid): crashes and return for the same env-step budget."
)

CONFIG = GymConfig

#: A unit's result (``run_unit``), what a kept one must hold (``runner.kept``'s schema).
UNIT_RESULT = {
    "crashes": COUNT,
    "crashes_per_1000": NON_NEGATIVE,
    "episodes": COUNT,
    "steps_to_threshold": (None, COUNT),
    "curve_steps": [COUNT],
    "curve_crashes": [COUNT],
    "curve_return": [NUMBER],
    "greedy_crash_rate": NON_NEGATIVE,
    "greedy_return": NUMBER,
    "wall_s": NON_NEGATIVE,
    "steps_per_s": NON_NEGATIVE,
    "oracle?": [[COUNT]],
    "actuator_names?": [TEXT],
    "sensor_names?": [TEXT],
    "structure?": [[COUNT]],
    "agrees_with_oracle?": [FLAG],
}


def prepare(config: GymConfig) -> None:
    """The world's extra (and SB3 when asked for) installed, else one ModuleNotFoundError."""
    require_extras([config.spec], sb3="sb3-dqn" in config.methods)


def processes(config: GymConfig, units: list[dict[str, Any]]) -> tuple[int, str]:
    """How many processes the units take by default: one per core where the world's env steps
    slowly (highway-env), else 1 (in-process); and why (``methods.units.world_processes``)."""
    return world_processes([config.spec], config.steps, len(units))


def units(config: GymConfig) -> list[dict[str, Any]]:
    """One unit per method and seed: ``{"id", "method", "seed_index"}``."""
    return [
        {"id": f"{method}-seed{index}", "method": method, "seed_index": index}
        for method in config.methods
        for index in range(config.seeds)
    ]


def work(config: GymConfig, unit: dict[str, Any]) -> int:
    """A unit's training env steps (what ``run_unit`` reports to ``progress``)."""
    return config.steps


def run_unit(
    config: GymConfig, unit: dict[str, Any], progress: Callable[[int], None] | None = None
) -> dict[str, Any]:
    """Train and evaluate one unit (one method, one seed): ``Recorder.result()`` with the greedy
    measures, ``wall_s`` and ``steps_per_s`` (and the structures, for Factor-Q)."""
    with torch_threads(1):
        return RUNNERS[unit["method"]](config, unit, progress or (lambda steps: None))


# --------------------------------------------------------------------------------------------
# Results (no torch below)

MEASURES = (
    "crashes_per_1000",
    "greedy_crash_rate",
    "greedy_return",
    "steps_to_threshold",
    "steps_per_s",
)


#: The measures that are proportions (per seed in [0, 1]): Wilson's interval.
PROPORTIONS = ("greedy_crash_rate",)
CURVES = ("curve_crashes", "curve_return")


def summarise(config: GymConfig, unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per method: each measure's mean and 95% interval over seeds (Wilson for the greedy crash
    rate, else the BCa bootstrap), the curves of every seed and their mean and band over seeds,
    and (learned dependencies) how many seeds' learner agrees with the oracle per actuator."""
    by_method: dict[str, list[dict[str, Any]]] = {}
    for unit, result in zip(units(config), unit_results, strict=True):
        by_method.setdefault(unit["method"], []).append(result)
    methods = {}
    for method, results in by_method.items():
        entry: dict[str, Any] = {
            name: seed_stat([r[name] for r in results], config.seed, name in PROPORTIONS)
            for name in MEASURES
        }
        entry["curves"] = {name: [r[name] for r in results] for name in ("curve_steps", *CURVES)}
        entry["bands"] = {name: seed_bands(entry["curves"][name], config.seed) for name in CURVES}
        entry["reached"] = sum(r["steps_to_threshold"] is not None for r in results)
        entry["wall_s"] = sum(r["wall_s"] for r in results)
        if "structure" in results[0]:
            entry["structures"] = [r["structure"] for r in results]
        if "agrees_with_oracle" in results[0]:
            per_actuator = zip(*(r["agrees_with_oracle"] for r in results), strict=True)
            entry["agrees_with_oracle"] = [sum(seeds) for seeds in per_actuator]
        methods[method] = entry
    out: dict[str, Any] = {
        "methods": methods,
        "world": config.spec.label,
        "threshold": config.return_threshold,
    }
    declared = next((r for r in unit_results if "oracle" in r), None)
    if declared is not None:
        out["sensors"] = declared["sensor_names"]
        out["actuators"] = declared["actuator_names"]
        out["oracle"] = declared["oracle"]
    return out


def run(config: GymConfig, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Every unit here, summarised into the runner's envelope (no files)."""
    return frame.run_in_process(sys.modules[__name__], config, progress)
