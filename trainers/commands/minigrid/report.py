"""``factorq minigrid``'s Markdown and figure, and its cells for ``factorq sweep``, from its
results alone (no torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from factorq_trainers.analysis.stats import TOO_LITTLE_DATA, count_ratio, format_number
from factorq_trainers.analysis.vocabulary import recorded_label
from factorq_trainers.methods.units import stat_cell as _cell
from factorq_trainers.methods.units import sweep_cell
from factorq_trainers.runner.results import new_figure

#: The issue's target: the learner finds forward <- front within this many env steps.
FOUND_TARGET_STEPS = 2_000


def markdown(results: dict[str, Any]) -> str:
    config = results["config"]
    seeds = config["seeds"]
    lines = [
        "# Factor-Q on MiniGrid Dynamic-Obstacles",
        "",
        f"{seeds} seeds per cell, means with 95% intervals across seeds (success rate: Wilson; "
        f"the others: BCa bootstrap; neither leaves the possible range); semantics "
        f"`{config['semantics']}`, sensors {', '.join(results['sensors'])}. Success rate, return "
        f"and steps to goal over the episodes ending in the last "
        f"{config['final_fraction']:.0%} of the budget; collisions over the whole budget; "
        f"'steps to 90%' over the seeds that got there (k/{seeds}); wall time for all seeds of "
        f"a method together. {results['notice']}. Exploration: tabular Factor-Q "
        f"{config.get('exploration', 'uniform')}, Q-learning and DQN uniform.",
        "",
    ]
    for size, per_method in results["results"].items():
        budget = results["budgets"][size]
        lines += [
            f"## {size}x{size} ({budget:,} env steps per seed)",
            "",
            "| method | success rate | return | steps to goal | collisions (training) | greedy "
            "collisions | env steps to 90% success | wall s | forward <- front found at |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for method, entry in per_method.items():
            s = entry["summary"]
            found = "-"
            if "found_forward_front" in s:
                found = (
                    f"{_cell(s['found_forward_front'], 0, seeds)}; "
                    f"{s['found_within_target']:.0%} within {FOUND_TARGET_STEPS:,}"
                )
            lines.append(
                f"| {recorded_label(results, method)} | {_cell(s['success_rate'], 2, seeds)} | "
                f"{_cell(s['return'], 2, seeds)} | {_cell(s['steps_to_goal'], 1, seeds)} | "
                f"{_cell(s['collisions'], 1)} | {_cell(s['greedy_collisions'], 1)} | "
                f"{_cell(s['steps_to_90'], 0, seeds)} | {format_number(s['wall_s'])} | {found} |"
            )
        lines += ["", *_targets(results, per_method), ""]
    wall_s = results["timing"]["wall_s"]
    lines.append(f"Total wall time {wall_s:.0f} s.")
    return "\n".join(lines) + "\n"


def _targets(results: dict[str, Any], per_method: dict[str, Any]) -> list[str]:
    """The issue's targets at one size, where the methods they compare ran."""
    out = []
    dqn = per_method.get("dqn", {}).get("summary")
    for method in ("factor-q-learned", "factor-q"):
        mine = per_method.get(method, {}).get("summary")
        if mine is None or dqn is None:
            continue
        ours, theirs = mine["collisions"]["mean"], dqn["collisions"]["mean"]
        ratio = count_ratio(theirs, ours)
        success_ok = (mine["success_rate"]["mean"] or 0.0) >= (dqn["success_rate"]["mean"] or 0.0)
        if ratio is None:
            compared = (
                f"{TOO_LITTLE_DATA} to compare training collisions with DQN's ({ours:.2f} "
                f"against {theirs:.2f})"
            )
        else:
            compared = (
                f"training collisions {ratio:.2f}x below DQN's (target >= 10x: "
                f"{'met' if ratio >= 10 else 'not met'})"
            )
        out.append(
            f"- {recorded_label(results, method)}: {compared}; success rate "
            f"{'no worse than' if success_ok else 'below'} DQN's."
        )
    return out


def figure(results: dict[str, Any], path: Path) -> None:
    panels = (
        ("success_rate", "success rate (end of training)", False),
        ("collisions", "collisions during training", True),
        ("steps_to_90", "env steps to 90% success", False),
    )
    figure = new_figure(figsize=(13, 4))
    sizes = list(results["results"])
    methods = list(results["config"]["methods"])
    for column, (measure, title, log) in enumerate(panels):
        axis = figure.add_subplot(1, len(panels), column + 1)
        for offset, method in enumerate(methods):
            xs, ys, errs = [], [], []
            for position, size in enumerate(sizes):
                stat = results["results"][size][method]["summary"][measure]
                if stat["mean"] is None:
                    continue
                xs.append(position + (offset - len(methods) / 2) * 0.06)
                ys.append(stat["mean"])
                ci = stat["ci95"]
                errs.append(0.0 if ci is None or ci[1] is None else ci[1] - stat["mean"])
            axis.errorbar(
                xs, ys, yerr=errs, marker="o", capsize=3, label=recorded_label(results, method)
            )
        axis.set_xticks(range(len(sizes)), [f"{s}x{s}" for s in sizes])
        axis.set_title(title)
        if log:
            axis.set_yscale("log")
        axis.grid(alpha=0.3)
    figure.axes[0].legend(fontsize=7)
    figure.suptitle(
        f"MiniGrid Dynamic-Obstacles, {results['config']['seeds']} seeds, "
        "95% intervals (Wilson, BCa bootstrap)"
    )
    figure.tight_layout()
    figure.savefig(path, dpi=100, format="png")


# --------------------------------------------------------------------------------------------
# factorq sweep --command minigrid

SWEEP_MEASURES = ("success_rate", "collisions", "greedy_collisions", "steps_to_90")


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per size and method of a ``minigrid.json`` dict: the ``SWEEP_MEASURES`` (means and 95%
    intervals across seeds)."""
    return {
        f"{size}x{size}/{method}": sweep_cell(
            f"{size}x{size}", method, entry["summary"], SWEEP_MEASURES
        )
        for size, per_method in results["results"].items()
        for method, entry in per_method.items()
    }
