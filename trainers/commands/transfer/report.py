"""``factorq transfer``'s Markdown and figure, from its results alone (no torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from factorq_trainers.analysis.stats import TOO_LITTLE_DATA
from factorq_trainers.analysis.vocabulary import label
from factorq_trainers.methods.units import stat_cell, sweep_cell
from factorq_trainers.runner.results import new_figure

#: The fresh method each carried one is measured against.
PAIRS = {"factor-q-body": "factor-q", "factor-q-learned-body": "factor-q-learned"}


def _cell(stat: dict[str, Any], digits: int = 1) -> str:
    low, high = stat["range"]
    return stat_cell(stat, digits) + f" ({low:.{digits}f}-{high:.{digits}f})"


def markdown(results: dict[str, Any]) -> str:
    """The report: per target regime, each method's measures and the body model's ratio."""
    config = results["config"]
    early, seeds = config["early"], config["seeds"]
    source = (
        f"learned by Factor-Q in {config['source_episodes']} episodes of the "
        f"{config['source_size']}x{config['source_size']} {config['source_regime']} grid "
        f"({config['source_obstacles']} obstacles, layout {config['source_layout_seed']})"
        if results["body_from"] != "file"
        else f"read from {config['body_model']}"
    )
    lines = [
        "# A body model learned once, carried into a new task",
        "",
        f"The body model (Factor-Q's local tables, eq. 5) {source}; the target task: the "
        f"{config['size']}x{config['size']} grid with {config['obstacles']} obstacles (layout "
        f"{config['layout_seed']}), {config['episodes']} episodes, {seeds} seeds, the same worlds "
        f"and policy streams for every method. Factor-Q explores {config['exploration']}, "
        f"Q-learning uniform. Means over seeds with 95% BCa bootstrap intervals and (in "
        f"parentheses) the range; path: {results['path']}.",
        "",
    ]
    for regime, methods in results["results"].items():
        lines += [
            f"## Target: {regime}",
            "",
            f"| method | collisions, first {early} episodes | collisions, last {early} | steps "
            f"per episode, last {early} | truncated, last {early} |",
            "|---|---|---|---|---|",
        ]
        for method, entry in methods.items():
            lines.append(
                f"| {label(method)} | {_cell(entry['early_collisions'])} | "
                f"{_cell(entry['late_collisions'])} | {_cell(entry['late_steps'])} | "
                f"{_cell(entry['late_truncated'], 2)} |"
            )
        for carried, per_regime in results["body_against_fresh"].items():
            against = per_regime.get(regime)
            if against is None:
                continue
            fresh = methods[PAIRS[carried]]["early_collisions"]["mean"]
            body = methods[carried]["early_collisions"]["mean"]
            ratio = against["early_collisions_ratio"]
            if ratio is not None:
                said = f"{ratio:.1f}x fewer"
            elif fresh > 0:
                said = "no"  # a ratio with a zero side is unbounded: both counts are given
            else:
                said = f"({TOO_LITTLE_DATA}: none either way)"
            verdict = "met" if against["target_met"] else "not met"
            lines += [
                "",
                f"- {label(carried)}: {said} collisions in the first {early} episodes "
                f"({body:.2f} against {fresh:.2f} per seed from scratch; target "
                f"{results['target_ratio']:.0f}x: {verdict}); steps per episode over the last "
                f"{early}: {against['late_steps_body']:.1f} against "
                f"{against['late_steps_fresh']:.1f} from scratch.",
            ]
        lines.append("")
    return "\n".join(lines)


def figure(results: dict[str, Any], path: Path) -> None:
    """Collisions per episode (mean over seeds) in the first episodes of the target, one panel
    per regime, each method a line (log scale: Q-learning's are hundreds of times more)."""
    regimes = list(results["results"])
    figure = new_figure(figsize=(4 * len(regimes), 3.6))
    shown = max(2 * results["config"]["early"], 1)
    for column, regime in enumerate(regimes):
        axis = figure.add_subplot(1, len(regimes), column + 1)
        for method, entry in results["results"][regime].items():
            curve = entry["collisions_per_episode"][:shown]
            axis.plot(range(1, len(curve) + 1), [value + 0.01 for value in curve],
                      label=label(method))  # fmt: skip
        axis.set_yscale("log")
        axis.set_xlabel("target episode")
        axis.set_title(f"target: {regime}")
        axis.grid(alpha=0.3)
    figure.axes[0].set_ylabel("collisions per episode (+0.01)")
    figure.axes[0].legend(fontsize=8)
    figure.suptitle("A body model carried into a new task: collisions, mean over seeds")
    figure.tight_layout()
    figure.savefig(path, dpi=100, format="png")


#: What ``factorq sweep --command transfer`` reports per configuration and (regime, method).
SWEEP_MEASURES = ("early_collisions", "late_collisions", "late_steps")


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per target regime and method of a ``transfer.json`` dict: the ``SWEEP_MEASURES`` (means
    and 95% intervals across seeds)."""
    return {
        f"{regime}/{method}": sweep_cell(regime, method, entry, SWEEP_MEASURES)
        for regime, methods in results["results"].items()
        for method, entry in methods.items()
    }
