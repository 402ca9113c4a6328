"""``risk``: torchrl's DQN alone against DQN + local risk, side by side: a command module of the
runner (``factorq_trainers.runner.frame``); ``RiskConfig`` and the names it checks against in
``config.py``, the methods in ``methods.py``, the Markdown, figure and sweep cells in
``report.py`` (without torch). The experiment, its measures and runs: the tutorial
``docs/tutorials/dqn-local-risk.md``.

One unit per (world, method, seed), each training torchrl's DQN recipe with the same budget,
network and seed; the methods differ only by the two lines of ``factorq_torch.risk``: ``dqn``
alone, ``dqn+risk`` (``LocalRisk`` over a ``LocalRewardTable`` on the env's true dependency,
trained by ``LocalRiskLoss``), ``dqn+risk-learned`` (over a ``StructureLearner``), and
``sb3-dqn`` / ``sb3-dqn+risk`` (Stable-Baselines3's DQN on the gymnasium grid, alone and with
``factorq_torch.integrations.sb3``). Every method reads the conventional reward
(``SplitLocalReward(keep_reward=True)``). On every world ``mask_threshold`` is half the collision
penalty (highway: 2/3), and on highway a success is an episode run to its time limit without a
crash.
"""

from __future__ import annotations

import itertools
import math
import statistics
import sys
from typing import Any

from factorq_trainers.analysis.stats import count_ratio
from factorq_trainers.commands.risk.config import OWN_WORLDS, Progress, RiskConfig
from factorq_trainers.commands.risk.methods import quiet_torchrl, run_sb3, run_torchrl
from factorq_trainers.methods.units import require_extras, world_processes
from factorq_trainers.runner import frame
from factorq_trainers.runner.kept import COUNT, FRACTION, NON_NEGATIVE, NUMBER, TEXT

NAME = "risk"
HELP = "torchrl's DQN (and SB3's) alone against DQN + local risk, side by side"
WORK_UNIT = "step"
CONFIG = RiskConfig

#: A unit's result (``run_unit``), what a kept one must hold (``runner.kept``'s schema).
UNIT_RESULT = {
    "world": TEXT,
    "method": TEXT,
    "seed": COUNT,
    "train_collisions": COUNT,
    "episodes": COUNT,
    "final_return": NUMBER,
    "steps_to_threshold": (None, COUNT),
    "greedy_collisions": COUNT,
    "greedy_success": FRACTION,
    "wall_s": NON_NEGATIVE,
    "risk_log?": [
        {
            "steps": COUNT,
            "risky_steps": COUNT,
            "overrides": COUNT,
            "penalised": {"*": COUNT},
            "mean_penalty": {"*": NUMBER},
        }
    ],
    "structure?": {
        "actuators": [TEXT],
        "parents": [(None, [TEXT])],
        "oracle": (None, [[TEXT]]),
    },
}


def prepare(config: RiskConfig) -> None:
    """The extras the asked-for worlds and methods need, else one ModuleNotFoundError naming
    the extra, before any work."""
    from factorq_envs.gymnasium_adapter import require_extra

    if "minigrid" in config.worlds:
        require_extra("minigrid", "factorq-torch[minigrid]")
    sb3 = any(method.startswith("sb3") for method in config.methods)
    require_extras(_declared(config), sb3=sb3 and bool(set(config.worlds) & set(config.sb3_worlds)))


def processes(config: RiskConfig, units: list[dict[str, Any]]) -> tuple[int, str]:
    """How many processes the units take by default: one per core where a declared world's env
    steps slowly (highway-env), else 1 (in-process); and why (``methods.units.world_processes``;
    the grid and MiniGrid step in microseconds: not measured)."""
    return world_processes(_declared(config), config.steps, len(units))


def _declared(config: RiskConfig) -> list[Any]:
    """The declared worlds among ``config.worlds`` (``factorq_envs.worlds``)."""
    from factorq_envs.worlds import resolve_world

    return [resolve_world(world) for world in config.worlds if world not in OWN_WORLDS]


def units(config: RiskConfig) -> list[dict[str, Any]]:
    """One unit per (world, method, seed); sb3 methods only on ``sb3_worlds``."""
    return [
        {"id": f"{world}/{method}/{seed}", "world": world, "method": method, "seed": seed}
        for world in config.worlds
        for method in config.methods
        if not (method.startswith("sb3") and world not in config.sb3_worlds)
        for seed in range(config.seed, config.seed + config.seeds)
    ]


def work(config: RiskConfig, unit: dict[str, Any]) -> int:
    """The unit's share of the progress bar: its training env steps (what ``run_unit`` reports)."""
    return config.steps


def run_unit(
    config: RiskConfig, unit: dict[str, Any], progress: Progress | None = None
) -> dict[str, Any]:
    """Train and evaluate one (world, method, seed), without torchrl's INFO lines
    (``quiet_torchrl``)."""
    run_method = run_sb3 if unit["method"].startswith("sb3") else run_torchrl
    with quiet_torchrl():
        result = run_method(config, unit, progress)
    return {**{key: unit[key] for key in ("world", "method", "seed")}, **result}


# --------------------------------------------------------------------------------------------
# Summary, report, figure (no torch)

METRICS = (
    "train_collisions",
    "greedy_collisions",
    "final_return",
    "greedy_success",
    "steps_to_threshold",
    "wall_s",
)


#: The ratios ``summarise`` reports per world: (first, second, its name, whose return gains):
#: the collisions of ``first`` over ``second``'s.
RATIOS = (
    ("dqn", "dqn+risk", "dqn / dqn+risk", "second"),
    ("dqn", "dqn+risk-learned", "dqn / dqn+risk-learned", "second"),
    ("sb3-dqn", "sb3-dqn+risk", "sb3-dqn / sb3-dqn+risk", "second"),
    ("dqn+risk-learned", "dqn+risk", "learned / oracle collisions", "first"),
)


def _mean(values: list[float | None]) -> float | None:
    found = [v for v in values if v is not None and not (isinstance(v, float) and math.isnan(v))]
    return statistics.fmean(found) if found else None


def summarise(config: RiskConfig, unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """Means over seeds per (world, method), the ratios the issue's targets name, the learned
    structures (``structures``, by unit id: what ``dqn+risk-learned`` committed to, beside the
    env's dependency) and the layer's logs (``risk_logs``)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for result in unit_results:
        groups.setdefault((result["world"], result["method"]), []).append(result)
    rows = []
    for (world, method), found in sorted(groups.items()):
        row: dict[str, Any] = {"world": world, "method": method, "seeds": len(found)}
        row.update({metric: _mean([r[metric] for r in found]) for metric in METRICS})
        row["reached"] = sum(r["steps_to_threshold"] is not None for r in found)
        rows.append(row)
    by = {(row["world"], row["method"]): row for row in rows}
    ratios = []
    for world, (first, second, pair, gain) in itertools.product(config.worlds, RATIOS):
        if (world, first) in by and (world, second) in by:
            one, other = by[world, first], by[world, second]
            gains, base = (other, one) if gain == "second" else (one, other)
            gained = (gains["final_return"], base["final_return"])  # None: no finished episode
            ratio = count_ratio(one["train_collisions"], other["train_collisions"])
            difference = None if None in gained else gained[0] - gained[1]
            ratios.append(
                {"world": world, "pair": pair, "collision_ratio": ratio, "return_gain": difference}
            )
    structures = {
        f"{r['world']}/{r['method']}/{r['seed']}": r["structure"]
        for r in unit_results
        if "structure" in r
    }
    return {"rows": rows, "ratios": ratios, "structures": structures, **risk_logs(unit_results)}


def risk_logs(unit_results: list[dict[str, Any]]) -> dict[str, Any]:
    """The layer's per-episode ``RiskSummary`` of every ``dqn+risk-*`` unit (``risk_log``, by
    unit id) and their totals per (world, method) over seeds (``risk_rows``): training episodes,
    steps, the share of steps it penalised an actuator, greedy choices it overrode per episode,
    and per actuator how often it was penalised and by how much on average."""
    log: dict[str, list[dict]] = {}
    groups: dict[tuple[str, str], list[dict]] = {}
    for result in unit_results:
        episodes = result.get("risk_log")
        if episodes is None:  # a method without the layer (or a unit kept before the log)
            continue
        log[f"{result['world']}/{result['method']}/{result['seed']}"] = episodes
        groups.setdefault((result["world"], result["method"]), []).extend(episodes)
    rows = []
    for (world, method), episodes in sorted(groups.items()):
        steps = sum(episode["steps"] for episode in episodes)
        counts: dict[str, int] = {}
        totals: dict[str, float] = {}
        for episode in episodes:
            for name, count in episode["penalised"].items():
                counts[name] = counts.get(name, 0) + count
                totals[name] = totals.get(name, 0.0) + count * episode["mean_penalty"][name]
        rows.append(
            {
                "world": world,
                "method": method,
                "episodes": len(episodes),
                "steps": steps,
                "penalised_share": sum(e["risky_steps"] for e in episodes) / max(steps, 1),
                "overrides_per_episode": sum(e["overrides"] for e in episodes)
                / max(len(episodes), 1),
                "penalised": counts,
                "mean_penalty": {
                    name: (totals[name] / counts[name] if counts[name] else 0.0) for name in counts
                },
            }
        )
    return {"risk_rows": rows, "risk_log": log}


def run(config: RiskConfig) -> dict[str, Any]:
    """All units here, summarised into the runner's envelope (no files)."""
    return frame.run_in_process(sys.modules[__name__], config)
