"""``factorq gym``'s Markdown and figure, and its cells for ``factorq sweep``, from its results
alone (no torch; the experiment is ``factorq_trainers.commands.gym.command``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from factorq_trainers.analysis.stats import TOO_LITTLE_DATA, count_ratio
from factorq_trainers.analysis.vocabulary import label
from factorq_trainers.methods.units import stat_cell as _cell
from factorq_trainers.methods.units import sweep_cell
from factorq_trainers.runner.results import new_figure

#: What ``factorq sweep --command gym`` reports per configuration (``sweep_cells``).
SWEEP_MEASURES = ("crashes_per_1000", "greedy_crash_rate", "greedy_return", "steps_to_threshold")
#: How the report names its intervals (``experiments.gym.summarise`` computes them).
INTERVALS = "greedy crash rate: Wilson; the others and the bands: BCa bootstrap"


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per method of a ``gym.json`` dict: the ``SWEEP_MEASURES`` (means and 95% intervals)."""
    world = results["world"]
    return {
        f"{world}/{method}": sweep_cell(world, method, entry, SWEEP_MEASURES)
        for method, entry in results["methods"].items()
    }


def targets(results: dict[str, Any]) -> list[str]:
    """The issue's targets, where the methods they compare ran."""
    methods = results["methods"]
    lines = []

    def crashes(method: str) -> float | None:
        return methods[method]["crashes_per_1000"]["mean"] if method in methods else None

    oracle, learned = crashes("factor-dqn"), crashes("factor-dqn-learned")
    for baseline in ("dqn", "sb3-dqn"):
        theirs = crashes(baseline)
        if oracle is None or theirs is None:
            continue
        ratio = count_ratio(theirs, oracle)
        mine = methods["factor-dqn"]["greedy_return"]["mean"]
        other = methods[baseline]["greedy_return"]["mean"]
        if ratio is None:
            compared = (
                f"{TOO_LITTLE_DATA} to compare training crashes with {label(baseline)} "
                f"({oracle:.2f} against {theirs:.2f} per 1000 steps)"
            )
        else:
            compared = (
                f"{ratio:.2f}x fewer training crashes than {label(baseline)} "
                f"(target >= 5x: {'met' if ratio >= 5 else 'not met'})"
            )
        lines.append(
            f"- Oracle Factor-Q: {compared}; greedy return {mine:.2f} against {other:.2f} "
            f"({'at least as high' if mine >= other else 'lower'})."
        )
    if oracle is not None and learned is not None:
        ratio = count_ratio(learned, oracle)
        if ratio is None:
            lines.append(
                f"- Learned dependencies: {TOO_LITTLE_DATA} to compare training crashes with the "
                f"oracle's ({learned:.2f} against {oracle:.2f} per 1000 steps)."
            )
        else:
            lines.append(
                f"- Learned dependencies: {ratio:.2f}x the oracle's training crashes (target <= "
                f"1.5x: {'met' if ratio <= 1.5 else 'not met'})."
            )
    return lines


def markdown(results: dict[str, Any]) -> str:
    """``gym.md``: one row per method, the targets, and the learned structures."""
    config = results["config"]
    seeds = config["seeds"]
    lines = [
        f"# Factor-Q on {results['world']}",
        "",
        f"{seeds} seeds per method, {config['steps']:,} training env steps each; means with 95% "
        f"intervals over seeds ({INTERVALS}; neither leaves the possible range). Greedy: "
        f"{config['eval_episodes']} episodes after training, exploration off. Steps to "
        f"threshold: first env step at which the mean return of the last {config['window']} "
        f"training episodes reached {results['threshold']:g} (k/{seeds} seeds got there). "
        f"Exploration: neural Factor-Q {config.get('exploration', 'uniform')}, DQN uniform.",
        "",
        "| method | crashes / 1,000 steps (training) | greedy crash rate | greedy return | "
        "steps to threshold | env steps/s | wall s (all seeds) |",
        "|---|---|---|---|---|---|---|",
    ]
    for method, entry in results["methods"].items():
        lines.append(
            f"| {label(method)} | {_cell(entry['crashes_per_1000'], 1)} | "
            f"{_cell(entry['greedy_crash_rate'])} | {_cell(entry['greedy_return'])} | "
            f"{_cell(entry['steps_to_threshold'], 0)} ({entry['reached']}/{seeds}) | "
            f"{_cell(entry['steps_per_s'], 1)} | {entry['wall_s']:.0f} |"
        )
    lines += ["", *targets(results)]
    learned = results["methods"].get("factor-dqn-learned")
    if learned is not None and "oracle" in results:
        agree = ", ".join(
            f"{name} {count}/{seeds}"
            for name, count in zip(results["actuators"], learned["agrees_with_oracle"], strict=True)
        )
        lines += ["", f"Learned structure equal to the oracle's row, per actuator: {agree}."]
    return "\n".join(lines) + "\n"


def figure(results: dict[str, Any], path: Path) -> None:
    """Crashes (cumulative) and return (last ``window`` episodes) against env steps, the mean
    over seeds with its 95% BCa bootstrap band (``summarise``'s ``bands``)."""
    figure = new_figure(figsize=(11, 4))
    panels = (("curve_crashes", "crashes during training"), ("curve_return", "training return"))
    for column, (name, title) in enumerate(panels):
        axis = figure.add_subplot(1, 2, column + 1)
        for method, entry in results["methods"].items():
            steps = entry["curves"]["curve_steps"][0]
            band = entry["bands"][name]
            # JSON's null as NaN: a gap in the line; a band's bound, the mean (no band there)
            means, low, high = (np.array(band[k], dtype=float) for k in ("mean", "low", "high"))
            axis.plot(steps, means, label=label(method))
            low, high = (np.where(np.isnan(bound), means, bound) for bound in (low, high))
            axis.fill_between(steps, low, high, alpha=0.2)
        axis.set_xlabel("env steps")
        axis.set_title(title)
        axis.grid(alpha=0.3)
    figure.axes[0].legend(fontsize=8)
    figure.suptitle(f"{results['world']}: mean over seeds, 95% BCa bootstrap bands")
    figure.tight_layout()
    figure.savefig(path, dpi=100, format="png")
