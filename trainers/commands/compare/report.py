"""The files of ``factorq compare``: ``comparison.json``, ``comparison.png``, ``comparison.md``.

Everything here reads the results dict of ``command.run`` beside it and computes nothing new; the
runner's frame writes the three files (``markdown``, ``figure``), and ``compare.finish`` the logs
(in ``LOGS_DIRECTORY``)."""

from __future__ import annotations

import functools
import os
from typing import Any

import numpy as np

from factorq_trainers.analysis import stats
from factorq_trainers.analysis.vocabulary import label
from factorq_trainers.methods.units import sweep_cell
from factorq_trainers.runner.results import body_label, new_figure

#: A method reached the threshold when an episode took at most this many times the shortest path.
THRESHOLD_FACTOR = 1.5
LOGS_DIRECTORY = "logs"
COLOURS = {
    "factor-q": "#0072B2",
    "q-learning": "#D55E00",
    "dqn": "#009E73",
    "factor-dqn": "#CC79A7",
}


def figure(results: dict[str, Any], path: str | os.PathLike) -> None:
    """Steps and collisions per episode against env steps, mean and 95% band, one column a world."""
    worlds = list(results["thresholds"])
    grid = np.asarray(results["curves"]["env_steps"])
    figure = new_figure(figsize=(4.2 * len(worlds), 7.0), layout="constrained")
    axes = figure.subplots(2, len(worlds), squeeze=False, sharex=True)
    rows = (("steps", "steps per episode"), ("collisions", "collisions per episode"))
    for column, world in enumerate(worlds):
        for row, (name, measure) in enumerate(rows):
            axis = axes[row][column]
            for method in results["results"]:
                curve = results["curves"][method][world][name]
                # null (no value) as NaN
                mean, low, high = (np.array(curve[k], dtype=float) for k in ("mean", "low", "high"))
                colour = COLOURS[method]
                floor = 1.0 if name == "steps" else 0.0  # a path takes >= 1 step
                axis.plot(grid, mean, color=colour, label=label(method), linewidth=1.4)
                axis.fill_between(grid, np.maximum(low, floor), high, color=colour, alpha=0.2)
            if name == "steps":
                axis.axhline(
                    results["thresholds"][world]["threshold"],
                    color="grey",
                    linestyle=":",
                    linewidth=1.0,
                    label=f"{THRESHOLD_FACTOR}x shortest path",
                )
                axis.set_title(f"{world} world")
                axis.set_yscale("log")
            else:  # symlog: linear near 0, where the Factor-Q curves end up
                axis.set_yscale("symlog", linthresh=1.0)
                axis.set_ylim(bottom=0.0)
            axis.set_xlim(0, grid[-1])
            axis.set_ylabel(measure)
            if row == len(rows) - 1:
                axis.set_xlabel("env steps per experiment")
    axes[0][0].legend(fontsize="small")
    body = body_label(results)
    figure.suptitle(
        ("" if body is None else f"{body}\n")
        + f"per-episode means over each 1/{grid.size} of the budget; mean over "
        f"{results['config']['seeds']} seeds with 95% bands",
        fontsize="medium",
    )
    figure.savefig(path, format="png", dpi=110)


def _number(value: float | None, digits: int = 0) -> str:
    return "never" if value is None else f"{value:,.{digits}f}"


def markdown(results: dict[str, Any]) -> str:
    """``comparison.md``: one row per method and world."""
    config = results["config"]
    body = body_label(results)
    lines = [
        "# factorq compare" if body is None else f"# factorq compare: {body}",
        "",
        f"{config['seeds']} seeds x {config['steps']:,} env steps per experiment, "
        f"{config['size']}x{config['size']} grid, {config['obstacles']} obstacles, "
        f"master seed {config['seed']}. Means over seeds (95% interval in brackets).",
        "",
        "- **steps to threshold**: env steps until the first episode whose path is within "
        f"{THRESHOLD_FACTOR}x the shortest path (static: BFS in the layout; moving worlds: the "
        "Manhattan distance); `never` unless every seed reached it (reached: seeds that did).",
        "- **collisions**, **greedy collisions** (on non-exploratory actions): totals over the "
        "budget; **avoidable**: the greedy collisions where some direction was free (not boxed in "
        "by walls and obstacles on all four sides). **final path**: mean path length of the "
        "episodes ending in the last 20% of the budget.",
        "- **wall s**: the method's batch (all worlds and seeds at once).",
        "",
        "| method | world | steps to threshold | reached | collisions | greedy collisions "
        "| avoidable | final path | wall s |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method, worlds in results["results"].items():
        for world, cell in worlds.items():
            low, high = cell["collisions_ci95"]
            g_low, g_high = cell["greedy_collisions_ci95"]
            seconds = "-" if cell["wall_s"] is None else f"{cell['wall_s']:.0f}"
            collisions = _number(cell["collisions"], 1)
            greedy = _number(cell["greedy_collisions"], 1)
            if low is not None:
                collisions += f" [{max(low, 0):,.0f}, {high:,.0f}]"
                greedy += f" [{max(g_low, 0):,.0f}, {g_high:,.0f}]"
            lines.append(
                f"| {label(method)} | {world} | {_number(cell['steps_to_threshold'])} "
                f"| {cell['seeds_reached']}/{config['seeds']} | {collisions} | {greedy} "
                f"| {_number(cell['avoidable_greedy_collisions'], 1)} "
                f"| {_number(cell['final_path_length'], 1)} | {seconds} |"
            )
    thresholds = ", ".join(
        f"{world} {entry['shortest_path']} -> {entry['threshold']:g}"
        for world, entry in results["thresholds"].items()
    )
    lines += ["", f"Shortest path -> threshold: {thresholds}.", ""]
    return "\n".join(lines)


#: What ``factorq sweep --command compare`` reports per method and world.
SWEEP_MEASURES = ("steps_to_threshold", "collisions", "greedy_collisions")


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per method and world of a ``comparison.json`` dict: its measures as means with 95%
    intervals across seeds (``steps_to_threshold`` only where every seed reached it)."""
    counted = ("collisions", "greedy_collisions", "avoidable_greedy_collisions")
    cells = {}
    for method, worlds in results["results"].items():
        for world, entry in worlds.items():
            reached = entry["steps_to_threshold_per_seed"]
            steps = {"mean": entry["steps_to_threshold"], "ci95": None}
            if entry["steps_to_threshold"] is not None:
                seed = results["config"].get("seed", 0)  # compare's bootstrap, its seed
                bounded = functools.partial(stats.bootstrap_mean_ci, seed=seed)
                steps["ci95"] = stats.interval(*stats.scalar_ci(reached, bounded)[1:])
            measures = {
                "steps_to_threshold": steps,
                **{
                    name: {"mean": entry[name], "ci95": stats.interval(*entry[f"{name}_ci95"])}
                    for name in counted
                },
            }
            cells[f"{world}/{method}"] = {
                **sweep_cell(world, method, measures, ("steps_to_threshold", *counted)),
                "seeds_reached": entry["seeds_reached"],
                "per_seed": {"steps_to_threshold": reached},
            }
    return cells


def results_problem(results: dict[str, Any]) -> str | None:
    """What is wrong with a ``comparison.json`` dict beyond its values' kinds (``factorq report``
    and a sweep's kept configurations check it): each method and regime holds one steps to the
    threshold per seed, and ``seeds_reached`` counts those reached; None when nothing is."""
    if not isinstance(results.get("results"), dict):
        return None
    config = results.get("config")
    seeds = config.get("seeds") if isinstance(config, dict) else None
    for method, regimes in results["results"].items():
        for regime, entry in regimes.items() if isinstance(regimes, dict) else ():
            if not isinstance(entry, dict) or "steps_to_threshold_per_seed" not in entry:
                continue
            per_seed = entry["steps_to_threshold_per_seed"]
            if not isinstance(per_seed, list) or (seeds is not None and len(per_seed) != seeds):
                count = len(per_seed) if isinstance(per_seed, list) else "no"
                return (
                    f"results/{method}/{regime} holds {count} seeds' steps to the threshold, "
                    f"not {seeds}"
                )
            reached = sum(step is not None for step in per_seed)
            if entry.get("seeds_reached") != reached:
                return (
                    f"results/{method}/{regime}/seeds_reached is {entry.get('seeds_reached')!r}, "
                    f"but {reached} seeds reached the threshold"
                )
    return None
