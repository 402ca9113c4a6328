"""``factorq risk``'s Markdown and figure, and its cells for ``factorq sweep``, from its results
alone (no torch; the experiment is ``factorq_trainers.commands.risk.command``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from factorq_torch.base.risk_text import summary_line
from factorq_trainers.analysis.stats import TOO_LITTLE_DATA
from factorq_trainers.methods.units import sweep_cell
from factorq_trainers.runner.results import new_figure

#: What ``factorq sweep --command risk`` reports per configuration (``sweep_cells``): means
#: over seeds (the summary keeps no interval).
SWEEP_MEASURES = ("train_collisions", "greedy_collisions", "final_return", "greedy_success")


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per world and method of a ``risk.json`` dict: the ``SWEEP_MEASURES``' means."""
    return {
        f"{row['world']}/{row['method']}": sweep_cell(
            row["world"], row["method"], row, SWEEP_MEASURES
        )
        for row in results["rows"]
    }


def _cell(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:,.{digits}f}"


def markdown(results: dict[str, Any]) -> str:
    """The table of means and the ratios."""
    config = results["config"]
    lines = [
        f"DQN alone vs DQN + local risk: {config['steps']:,} env steps per unit, "
        f"{config['seeds']} seeds, means over seeds.",
        "",
        "| world | method | training collisions | greedy collisions | final return | greedy "
        "success | steps to threshold (reached) | wall s |",
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for row in results["rows"]:
        lines.append(
            f"| {row['world']} | {row['method']} | {_cell(row['train_collisions'])} | "
            f"{_cell(row['greedy_collisions'])} | {_cell(row['final_return'], 2)} | "
            f"{_cell(row['greedy_success'], 2)} | {_cell(row['steps_to_threshold'], 0)} "
            f"({row['reached']}/{row['seeds']}) | {_cell(row['wall_s'])} |"
        )
    if results["ratios"]:
        lines += [
            "",
            "| world | ratio | collisions | return difference |",
            "| --- | --- | ---: | ---: |",
        ]
        for ratio in results["ratios"]:
            times, gain = ratio["collision_ratio"], ratio["return_gain"]  # None: a side had none
            lines.append(
                f"| {ratio['world']} | {ratio['pair']} | "
                + (TOO_LITTLE_DATA if times is None else f"{times:.1f}x")  # (``count_ratio``)
                + f" | {'-' if gain is None else f'{gain:+.2f}'} |"
            )
    lines += _risk_markdown(results)
    lines += _structure_markdown(results)
    return "\n".join(lines) + "\n"


def _structure_markdown(results: dict[str, Any]) -> list[str]:
    """Per ``dqn+risk-learned`` unit, the actuators whose committed parents differ from the
    env's dependency (or are still open): the disagreements stay visible."""
    structures = results.get("structures") or {}
    if not structures:
        return []
    lines = ["", "Learned structures against the env's dependency (actuators that differ):", ""]
    for unit_id, found in structures.items():
        oracle = found["oracle"]
        differ = []
        for name, parents, believed in zip(
            found["actuators"],
            found["parents"],
            oracle or [None] * len(found["actuators"]),
            strict=True,
        ):
            if parents is None:
                differ.append(f"{name} open")
            elif oracle is not None and sorted(parents) != sorted(believed):
                differ.append(
                    f"{name} <- {', '.join(parents) or 'none'} (oracle: "
                    f"{', '.join(believed) or 'none'})"
                )
            elif oracle is None:
                differ.append(f"{name} <- {', '.join(parents) or 'none'}")
        lines.append(f"- {unit_id}: {'; '.join(differ) or 'all as the oracle'}")
    return lines


def _risk_markdown(results: dict[str, Any]) -> list[str]:
    """What the layer did (``risk_rows``), and the last training episode's summary line of each
    (world, method)'s first seed, as ``RiskSummary.line`` writes it."""
    rows = results.get("risk_rows") or []
    if not rows:
        return []
    lines = [
        "",
        "What the layer did in training (`RiskSummary` per episode; totals over seeds):",
        "",
        "| world | method | episodes | steps penalised | overrides per episode | penalised "
        "(times, mean penalty) |",
        "| --- | --- | ---: | ---: | ---: | --- |",
    ]
    for row in rows:
        hits = ", ".join(
            f"{name} x{count:,} ({row['mean_penalty'][name]:.2f})"
            for name, count in sorted(row["penalised"].items(), key=lambda item: -item[1])
            if count
        )
        lines.append(
            f"| {row['world']} | {row['method']} | {row['episodes']:,} | "
            f"{row['penalised_share']:.1%} | {row['overrides_per_episode']:.2f} | {hits or '-'} |"
        )
    log = results.get("risk_log") or {}
    last: dict[tuple[str, str], dict[str, Any]] = {}
    for unit_id, episodes in log.items():  # the first seed of each (world, method)
        world, method, _ = unit_id.rsplit("/", 2)
        if episodes and (world, method) not in last:
            last[world, method] = episodes[-1]
    if last:
        lines += ["", "Last training episode of the first seed:", ""]
        lines += [
            f"- {world} {method}: {summary_line(summary)}"
            for (world, method), summary in last.items()
        ]
    return lines


def figure(results: dict[str, Any], path: Path) -> None:
    """Training collisions and final return per method, one panel pair per world."""
    worlds = sorted({row["world"] for row in results["rows"]})
    figure = new_figure(figsize=(4.5 * len(worlds), 6))
    axes = figure.subplots(2, len(worlds), squeeze=False)
    for column, world in enumerate(worlds):
        rows = [row for row in results["rows"] if row["world"] == world]
        labels = [row["method"] for row in rows]
        for line, (metric, title) in enumerate(
            (("train_collisions", "training collisions"), ("final_return", "final return"))
        ):
            axis = axes[line][column]
            axis.bar(range(len(rows)), [row[metric] or 0.0 for row in rows], color="tab:blue")
            axis.set_xticks(range(len(rows)), labels, rotation=30, ha="right", fontsize=8)
            axis.set_title(f"{world}: {title}", fontsize=9)
            if metric == "train_collisions":
                axis.set_yscale("log")
    figure.tight_layout()
    figure.savefig(path, dpi=100, format="png")  # the runner writes a temporary name first
