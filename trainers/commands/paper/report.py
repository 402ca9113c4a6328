"""The paper's output files: ``results.json``, Figure 3 and the claims report.

The runner writes all three from the results dict of ``factorq paper`` (``markdown``,
``figure``); ``factorq report`` redraws the figure and the report from ``results.json`` alone,
checked against the paper's schema first (``results_problem``).
Everything here reads the results and computes nothing new: the numbers in the report are the
numbers in the file.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

from factorq_envs.regimes import REGIME_PERIODS, REGIMES
from factorq_trainers.analysis.claims import ALGORITHM_LABELS, MEASURE_LABELS, MEASURES
from factorq_trainers.analysis.stats import with_ci
from factorq_trainers.commands.paper import figure as paper_figure
from factorq_trainers.commands.paper.figure_process import FigureProcess, FigureProcessError
from factorq_trainers.commands.paper.schema import escape_markdown, markdown_code
from factorq_trainers.commands.paper.schema import results_problem as results_problem
from factorq_trainers.runner.results import body_label, temporary_path

FIGURE_FILE = "figure3.png"


def figure3(results: dict[str, Any], path: str | os.PathLike) -> None:
    """The paper's Figure 3 of ``results`` as a PNG at ``path`` (``paper.figure.draw``)."""
    paper_figure.draw(results, path, *figure_arguments(results))


def figure_arguments(results: dict[str, Any]) -> tuple[list[str], list[str]]:
    """``paper_figure.draw``'s arguments after the path: the worlds and algorithms present, in
    canonical order."""
    config = results["config"]
    worlds = [world for world in REGIMES if world in config["regimes"]]
    algorithms = [name for name in ALGORITHM_LABELS if name in config["methods"]]
    return worlds, algorithms


def claim_value(claim: dict[str, Any]) -> str:
    """The claim's measured value with its 95% CI, for people (``not evaluated`` if missing)."""
    value, ci = claim["value"], claim["ci95"]
    if value is None:
        return "not evaluated"
    if isinstance(value, dict):
        return "; ".join(
            f"{ALGORITHM_LABELS[key]} {with_ci(item, None if ci is None else ci[key])}"
            for key, item in value.items()
        )
    return with_ci(value, ci)


def verdict(claim: dict[str, Any]) -> str:
    """``pass``, ``FAIL`` or ``n/a`` (not evaluated)."""
    return {True: "pass", False: "FAIL", None: "n/a"}[claim["pass"]]


def markdown(results: dict[str, Any]) -> str:
    """The report: claims, per-cell measures, the configuration, software and wall time."""
    config, claims = results["config"], results["claims"]
    worlds, algorithms = figure_arguments(results)
    passed = sum(claim["pass"] is True for claim in claims.values())
    evaluated = sum(claim["pass"] is not None for claim in claims.values())
    body = body_label(results)
    title = "# Factor-Q vs Q-learning: the paper's experiment"
    lines = [
        title if body is None else f"{title} ({escape_markdown(body)})",
        "",
        f"{passed} of {evaluated} evaluated claims pass ({len(claims)} claims). "
        f"{config['seeds']} independent experiments (seeds) per cell, each {config['runs']} runs "
        f"x {config['episodes']} episodes. Values are means with 95% confidence intervals "
        "across seeds.",
        "",
        "## Claims (SPEC section 5)",
        "",
        "| claim | statement | measured [95% CI] | threshold | result |",
        "| --- | --- | --- | --- | --- |",
    ]
    for name, claim in claims.items():
        lines.append(
            f"| {name} | {escape_markdown(claim['statement'])} | {claim_value(claim)} "
            f"| {escape_markdown(claim['threshold'])} "
            f"| {verdict(claim)} |"
        )
    lines += ["", "Details:", ""]
    for name, claim in claims.items():
        lines.append(f"- **{name}** ({verdict(claim)}): {escape_markdown(claim['detail'])}")
        for measure in claim["measures"]:
            mark = {True: "", False: " (fails)", None: ""}[measure["pass"]]
            lines.append(
                f"  - {escape_markdown(measure['name'])}: "
                f"{with_ci(measure['value'], measure['ci95'])}{mark}"
            )
    lines += [
        "",
        "## Per cell: per run (totals over the episodes of a run, mean over runs and seeds)",
        "",
        "| world | algorithm | "
        + " | ".join(MEASURE_LABELS[measure] for measure in MEASURES)
        + " | task return |",
        "| --- | --- | " + " | ".join("---:" for _ in MEASURES) + " | ---: |",
    ]
    for world in worlds:
        for algorithm in algorithms:
            summary = results["cells"][f"{world}/{algorithm}"]["summary"]
            values = [
                with_ci(summary[measure]["mean"], summary[measure]["ci95"])
                for measure in (*MEASURES, "task_return")
            ]
            lines.append(
                f"| {world} | {ALGORITHM_LABELS[algorithm]} | " + " | ".join(values) + " |"
            )
    lines += [
        "",
        f"Obstacle periods: {', '.join(f'{world} {REGIME_PERIODS[world]}' for world in worlds)} "
        "(0 never moves, k moves after every k-th action).",
        "",
        f"![Figure 3: steps and collisions per episode]({FIGURE_FILE})",
        "",
        "Figure 3: per world, steps per episode (top) and collisions per episode (bottom; solid "
        "all, dashed greedy, i.e. on actions that were not exploratory), each the mean over seeds "
        "and runs with a 95% confidence band across seeds. Both axes are logarithmic; the "
        "collision axis turns linear below the smallest non-zero mean so that zero stays visible. "
        "Q-learning's greedy collisions nearly coincide with all its collisions.",
        "",
        "## Statistics",
        "",
    ]
    statistics = results.get("statistics", {})
    lines += [
        f"- means: {statistics.get('means', 'n/a')}",
        f"- claims: {statistics.get('claims', 'n/a')}",
        "",
        "## Configuration",
        "",
        "| option | value |",
        "| --- | --- |",
    ]
    for key, value in config.items():
        shown = ",".join(map(str, value)) if isinstance(value, list) else value
        lines.append(f"| {markdown_code('--' + key.replace('_', '-'))} | {markdown_code(shown)} |")
    lines += ["", "## Software", "", "| package | version |", "| --- | --- |"]
    for package, version in results.get("software", {}).items():
        lines.append(f"| {escape_markdown(package)} | {escape_markdown(version)} |")
    timing = results.get("timing", {})
    lines += ["", "## Timing", ""]
    if timing:
        rate = timing["env_steps"] / max(timing["wall_s"], 1e-9)
        lines.append(
            f"Wall time {timing['wall_s']:.1f} s on the {escape_markdown(timing['backend'])} "
            f"backend with {timing['threads']} thread(s): {timing['env_steps']} environment "
            f"steps, {rate:.0f} steps/s."
        )
    else:
        lines.append("not recorded")
    return "\n".join(lines) + "\n"


#: What ``factorq sweep`` reports per configuration: the paper's measures per run.
SWEEP_MEASURES = MEASURES


def sweep_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per world and algorithm of a ``results.json`` dict: its per-run summary (means with 95%
    intervals) and per-seed values (``factorq sweep``'s rows; the claims go beside them)."""
    return {
        name: {
            "world": cell["world"],
            "algorithm": cell["algorithm"],
            **cell["summary"],
            "per_seed": cell["per_seed"],
        }
        for name, cell in results["cells"].items()
    }


def send_figure(
    figure_process: FigureProcess, results: dict[str, Any], out_dir: str | os.PathLike
) -> None:
    """Have ``figure_process`` draw Figure 3 of ``results`` into the temporary of
    ``out_dir/figure3.png``, which the runner then renames into place with the other files."""
    figure_process.send(
        paper_figure.drawn_part(results),
        temporary_path(Path(out_dir) / FIGURE_FILE),
        *figure_arguments(results),
    )


def figure(
    results: dict[str, Any], path: str | os.PathLike, figure_process: FigureProcess | None = None
) -> None:
    """Figure 3 of ``results`` at ``path``: by ``figure_process`` (``send_figure`` first) where
    one is given, here where it fails (a one-line notice says why) or none is."""
    if figure_process is not None:
        try:
            figure_process.finish(Path(path))
            return
        except FigureProcessError as error:
            print(f"factorq: {error}; drawing {FIGURE_FILE} here instead", file=sys.stderr)
    figure3(results, path)
