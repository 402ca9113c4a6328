"""``factorq dependencies``' Markdown and figure, from its results alone (no torch)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from factorq_trainers.analysis.stats import format_number, interval, with_ci
from factorq_trainers.analysis.vocabulary import recorded_label
from factorq_trainers.methods.units import sweep_cell
from factorq_trainers.runner.results import new_figure


def _percent_interval(bounds: list[float | None] | None) -> str:
    """``[lo, hi]% `` of a Wilson interval (nothing where it is undefined)."""
    if bounds is None or bounds[0] is None or bounds[1] is None:
        return ""
    return f"[{100 * bounds[0]:.0f}, {100 * bounds[1]:.0f}] "


def _against_cells(against: dict[str, Any]) -> str:
    """The learned / oracle cells of a row: the three ratios (collisions, greedy, learning
    speed), then the absolute task measures of both (steps per episode, episodes truncated)."""
    entries = [against.get(name) for name in ("collisions", "greedy_collisions", "learning_speed")]
    cells = ["n/a" if e is None else with_ci(e["ratio"], e.get("ci")) for e in entries]
    absolute = against.get("absolute")  # none where the oracle did not run
    if absolute is None:
        return " | ".join([*cells, "n/a", "n/a"])
    (mine, steps), (_, oracle_steps) = absolute["steps_per_episode"].items()
    truncated = absolute["fraction_truncated"]
    cells.append(f"{format_number(steps)} / {format_number(oracle_steps)}")
    cells.append(f"{100 * truncated[mine]:.0f}% / {100 * truncated['factor-q']:.0f}%")
    return " | ".join(cells)


def _percent(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.0f}%"


def markdown(results: dict[str, Any]) -> str:
    """The table of the issue's metrics, one row per setting, and the baselines' totals."""
    config, regimes = results["config"], results["config"]["regimes"]
    lines = [
        "# Learned sensor-actuator dependencies",
        "",
        f"{config['seeds']} experiments per setting, {config['runs']} runs x {config['episodes']} "
        f"episodes each, {', '.join(regimes)} regime{'s' * (len(regimes) > 1)}, "
        f"grid {config['size']}x{config['size']} with "
        f"{config['obstacles']} obstacles, Bayes factor {format_number(config['bayes_factor'])}, "
        f"Beta({format_number(config['prior_a'])}, {format_number(config['prior_b'])}) prior, "
        f"candidate prior {config['candidate_prior']}, "
        f"{config.get('likelihood', 'pattern')} likelihood, "
        f"{config.get('pairs', 'all')} pairs"
        + (
            f", reopening at Bayes factor {format_number(config['reopen_factor'])}"
            if config.get("reopen_factor") is not None
            else ""
        )
        + (
            f", at {format_number(config['noisy_reopen_factor'])} once sensors read wrong"
            if config.get("noisy_reopen_factor") is not None
            else ""
        )
        + "; "
        f"wall time {results['timing']['wall_s']:.1f} s. Factor-Q (learned, oracle, joint, gated): "
        "eqs. 2-3 "
        + (
            "under the risk gate (local values within 0.5 of 0 count as 0)"
            if config.get("risk_gate", "off") == "on"
            else "as the paper's"
        )
        + f", {config.get('exploration', 'uniform')} exploration; Q-learning and DQN explore "
        "uniformly.",
        "",
        "| setting | samples until right (median, p90) | right within target | wrong commitments "
        "/ 1000 | SHD at end | collisions vs oracle | greedy collisions vs oracle | learning speed "
        "vs oracle | steps per episode, learned / oracle | episodes truncated, learned / oracle |",
        "| --- | --- | --- | ---: | ---: | --- | --- | --- | --- | --- |",
    ]
    for setting, summary in results["settings"].items():
        structure = summary.get("structure")
        if structure is None:
            continue
        against = summary.get("against_oracle", {})
        lines.append(
            f"| {setting} | {format_number(structure['samples_until_right_median'])}, "
            f"{format_number(structure['samples_until_right_p90'])} | "
            f"{100 * structure['fraction_right_within_target']:.0f}% "
            f"{_percent_interval(structure.get('fraction_right_within_target_ci95'))}"
            f"(<= {structure['samples_target']}) | "
            f"{format_number(structure['wrong_commitments_per_1000'])} | "
            f"{format_number(structure['hamming_at_end_mean'])} | "
            f"{_against_cells(against)} |"
        )
    for setting, summary in results["settings"].items():
        gated = summary.get("gated_structure")
        if gated is None:
            continue
        against = summary.get("gated_against_oracle", {})
        lines.append(
            f"| {setting}, gated network | - | "
            f"{100 * gated['fraction_right_at_end']:.0f}% (at the end) | - | "
            f"{format_number(gated['hamming_at_end_mean'])} | "
            f"{_against_cells(against)} |"
        )
    lines += [
        "",
        "Per experiment (means): collisions, greedy collisions, env steps per run and per "
        f"episode, episodes truncated (not at the goal after {config['max_steps']} steps).",
        "",
        "| setting | method | collisions | greedy collisions | steps per run | steps per episode "
        "| episodes truncated |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for setting, summary in results["settings"].items():
        for method, entry in summary["methods"].items():
            lines.append(
                f"| {setting} | {recorded_label(results, method)} | "
                f"{format_number(entry['collisions_per_experiment'])} | "
                f"{format_number(entry['greedy_collisions_per_experiment'])} | "
                f"{format_number(entry['steps_per_run'])} | "
                f"{format_number(entry.get('steps_per_episode'))} | "
                f"{_percent(entry.get('fraction_truncated'))} |"
            )
    for setting, summary in results["settings"].items():
        entry = summary["methods"].get("dqn")
        if entry is not None:
            lines.append(
                f"\nDQN in {setting}: a budget of {entry['step_budget']} env steps per experiment "
                f"(the oracle's mean), {format_number(entry['episodes_per_experiment'])} episodes "
                f"per experiment on average; no runs, so no steps per run."
            )
    for setting, skipped in results.get("skipped", {}).items():
        for method, reason in skipped.items():
            lines.append(f"\nNot run: {recorded_label(results, method)} in {setting}: {reason}.")
    return "\n".join(lines) + "\n"


def figure(results: dict[str, Any], path: Path) -> None:
    """Top: fraction of experiments holding the right structure against env steps, per setting;
    bottom: collisions per episode per method."""
    settings, methods = list(results["settings"]), list(results["methods"])
    figure = new_figure(figsize=(3.2 * max(len(settings), 1), 6.0), layout="constrained")
    axes = figure.subplots(2, max(len(settings), 1), squeeze=False)
    for column, setting in enumerate(settings):
        summary = results["settings"][setting]
        top, bottom = axes[0, column], axes[1, column]
        structure = summary.get("structure")
        if structure is not None:
            curve = structure["curve"]
            top.plot(curve["env_steps"], curve["fraction_right"], color="C0")
        top.set_title(setting)
        top.set_ylim(-0.02, 1.02)
        top.set_xlabel("env steps")
        if column == 0:
            top.set_ylabel("fraction with the right structure")
        for method, entry in summary["methods"].items():
            values = entry["collisions_per_episode"]
            # one colour per method in every panel
            color = f"C{methods.index(method) if method in methods else len(methods)}"
            bottom.plot(
                range(1, len(values) + 1),
                values,
                label=recorded_label(results, method),
                color=color,
            )
        bottom.set_yscale("symlog", linthresh=1.0)
        bottom.set_xlabel("episode")
        if column == 0:
            bottom.set_ylabel("collisions per episode")
            bottom.legend(fontsize="small")
    figure.savefig(path, format="png", dpi=110)


# --------------------------------------------------------------------------------------------
# factorq sweep --command dependencies

#: What a dependencies sweep reports per setting and method (``experiments.dependencies``'
#: measures; the last two for the learned structure only).
SWEEP_MEASURES = (
    "collisions",
    "greedy_collisions",
    "fraction_right_within_target",
    "collisions_vs_oracle",
)


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per setting and method of a ``dependencies.json`` dict: collisions and greedy collisions
    per experiment (means), and for the learned structure the fraction right within the target
    and its collisions against the oracle's (ratio with its paired-bootstrap interval)."""
    cells = {}
    for setting, summary in results["settings"].items():
        structure = summary.get("structure")
        ratio = summary.get("against_oracle", {}).get("collisions")
        for method, entry in summary["methods"].items():
            learned = method == "factor-q-learned"
            measures = {  # bare means: no interval
                "collisions": entry["collisions_per_experiment"],
                "greedy_collisions": entry["greedy_collisions_per_experiment"],
                "fraction_right_within_target": structure["fraction_right_within_target"]
                if learned and structure
                else None,
                "collisions_vs_oracle": {
                    "mean": ratio["ratio"] if learned and ratio else None,
                    "ci95": interval(*ratio["ci"]) if learned and ratio and ratio["ci"] else None,
                },
            }
            cells[f"{setting}/{method}"] = sweep_cell(setting, method, measures, SWEEP_MEASURES)
    return cells
