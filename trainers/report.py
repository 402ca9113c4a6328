"""The paper's output files: ``results.json``, Figure 3 and the claims report.

``write_results`` writes all three from the results dict of ``factorq_trainers.paper.run``;
``factorq report`` (``regenerate``) redraws the figure and the report from ``results.json`` alone.
Everything here reads the results and computes nothing new: the numbers in the report are the
numbers in the file.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from factorq_envs.world import WORLD_PERIODS, WORLDS
from factorq_trainers.claims import ALGORITHM_LABELS, MEASURE_LABELS, MEASURES
from factorq_trainers.results import body_label, dumps, write_all_atomic
from factorq_trainers.schema import escape_markdown, load_results_file, markdown_code
from factorq_trainers.stats import format_number

RESULTS_FILE = "results.json"
FIGURE_FILE = "figure3.png"
REPORT_FILE = "report.md"

COLOURS = {"q-learning": "#D55E00", "factor-q": "#0072B2"}  # colour-blind safe (Okabe-Ito)
# Greedy collisions: a darker shade of the algorithm's colour, dashed, drawn over all collisions
# (for Q-learning the two nearly coincide, and the dashes must stay visible).
GREEDY_COLOURS = {"q-learning": "#7A3500", "factor-q": "#003A5C"}
WORLD_TITLES = {
    "static": "static world",
    "semi-dynamic": "semi-dynamic world (obstacles move every 10 steps)",
    "dynamic": "dynamic world (obstacles move every step)",
}


def _ordered_cells(results: dict[str, Any]) -> tuple[list[str], list[str]]:
    """The worlds and algorithms present in ``results``, in canonical order."""
    config = results["config"]
    worlds = [world for world in WORLDS if world in config["worlds"]]
    algorithms = [name for name in ALGORITHM_LABELS if name in config["algorithms"]]
    return worlds, algorithms


def preload_figure() -> None:
    """Import matplotlib's modules for ``figure3`` (about 0.4 s). ``factorq paper`` calls it in a
    background thread while the experiment runs, so that the figure does not wait for them."""
    import matplotlib.backends.backend_agg
    import matplotlib.figure
    import matplotlib.lines
    import matplotlib.ticker  # noqa: F401


def figure3(results: dict[str, Any], path: str | os.PathLike) -> None:
    """Draw the paper's Figure 3 from ``results`` and save it as a PNG at ``path``.

    Columns are worlds; the top row shows steps per episode, the bottom row collisions per
    episode (solid: all, dashed: greedy) on a log scale, each the mean over seeds and runs with
    its 95% confidence band across seeds.
    """
    # matplotlib loads here, not with the module: `factorq` starts faster without it.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    plain = FuncFormatter(lambda value, _: f"{value:g}")  # 0.01, 1, 300 rather than 10^-2, 3x10^2
    worlds, algorithms = _ordered_cells(results)
    config = results["config"]
    width, height = max(4.4 * len(worlds) + 0.6, 6.0), 7.4
    figure = Figure(figsize=(width, height), dpi=150)
    FigureCanvasAgg(figure)
    # Fixed margins (inches) rather than a constrained layout, which draws every tick twice
    # (half of the figure's time): room for the y labels, the title above, the legend below.
    axes = figure.subplots(
        2,
        len(worlds),
        sharex=True,
        sharey="row",
        squeeze=False,
        gridspec_kw={
            "left": 0.75 / width,
            "right": 1 - 0.3 / width,
            "top": 1 - 0.95 / height,
            "bottom": 1.0 / height,
            "wspace": 0.06,
            "hspace": 0.06,
        },
    )
    # The smallest non-zero mean over seeds x runs; below it a log axis turns linear, so episodes
    # with no collision at all stay on the plot.
    resolution = 1.0 / (config["seeds"] * config["runs"])
    highest = 0.0
    for column, world in enumerate(worlds):
        steps_axis, collisions_axis = axes[0, column], axes[1, column]
        for algorithm in algorithms:
            cell = results["cells"][f"{world}/{algorithm}"]
            colour = COLOURS[algorithm]
            _curve(steps_axis, cell, "steps", colour, "-", 1.6, band_alpha=0.25)
            _curve(collisions_axis, cell, "collisions", colour, "-", 1.6, band_alpha=0.25)
            greedy = GREEDY_COLOURS[algorithm]
            _curve(collisions_axis, cell, "greedy_collisions", greedy, "--", 1.1, band_alpha=0.12)
            highest = max(highest, max(cell["curves"]["collisions"]))
        # y given: matplotlib then skips placing the title around tick labels (there are none
        # above the axes), a fifth of the figure's drawing time
        steps_axis.set_title(WORLD_TITLES[world], fontsize=11, y=1.0, pad=6.0)
        steps_axis.set_yscale("log")
        steps_axis.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 3.0, 5.0)))
        collisions_axis.set_yscale("symlog", linthresh=resolution, linscale=0.5)
        collisions_axis.set_xlabel("episode")
        for axis in (steps_axis, collisions_axis):
            axis.grid(True, which="major", alpha=0.3)
            axis.set_xlim(1, config["episodes"])
            axis.yaxis.set_major_formatter(plain)
            axis.yaxis.set_minor_formatter(NullFormatter())
    axes[1, 0].set_ylim(0, max(highest, resolution) * 1.5)  # the row shares its y axis
    axes[0, 0].set_ylabel("steps per episode (log)")
    axes[1, 0].set_ylabel("collisions per episode (log)")
    handles = [
        Line2D([], [], color=COLOURS[name], lw=2, label=ALGORITHM_LABELS[name])
        for name in algorithms
    ] + [
        Line2D([], [], color="0.45", lw=1.6, ls="-", label="all collisions"),
        Line2D([], [], color="0.15", lw=1.1, ls="--", label="greedy collisions (not exploratory)"),
    ]
    columns = len(handles) if len(worlds) > 1 else 2
    figure.legend(
        handles=handles,
        loc="lower center",
        bbox_to_anchor=(0.5, 0.0),
        ncols=columns,
        frameon=False,
    )
    size = config["size"]
    body = body_label(results)
    if results.get("world") is not None:  # another world than the grid: its name and options
        where = body
    else:
        where = f"{size}\u00d7{size} grid with {config['obstacles']} obstacles"
        where += f", {body}" if body else ""
    figure.suptitle(
        f"Q-learning vs Factor-Q, {where}\n"
        f"mean of {config['seeds']} seeds \u00d7 {config['runs']} runs per episode, "
        "95% confidence bands across seeds",
        fontsize=11,
        y=1 - 0.08 / height,
        va="top",
    )
    # zlib level 1: a slightly larger file, encoded several times faster.
    figure.savefig(path, format="png", dpi=150, pil_kwargs={"compress_level": 1})


def _curve(axis, cell, name: str, colour: str, style: str, width: float, band_alpha: float) -> None:
    mean = np.asarray(cell["curves"][name], dtype=np.float64)
    episodes = np.arange(1, mean.size + 1)
    axis.plot(episodes, mean, color=colour, ls=style, lw=width, zorder=3 if style == "--" else 2)
    low, high = cell["curves_ci_low"][name], cell["curves_ci_high"][name]
    if low is not None:
        low = np.maximum(np.asarray(low, dtype=np.float64), 0.0)  # counts are never negative
        axis.fill_between(episodes, low, high, color=colour, alpha=band_alpha, lw=0)


def _with_ci(value: Any, ci: Any) -> str:
    if ci is None:
        return format_number(value)
    return f"{format_number(value)} [{format_number(ci[0])}, {format_number(ci[1])}]"


def claim_value(claim: dict[str, Any]) -> str:
    """The claim's measured value with its 95% CI, for people (``not evaluated`` if missing)."""
    value, ci = claim["value"], claim["ci95"]
    if value is None:
        return "not evaluated"
    if isinstance(value, dict):
        return "; ".join(
            f"{ALGORITHM_LABELS[key]} {_with_ci(item, None if ci is None else ci[key])}"
            for key, item in value.items()
        )
    return _with_ci(value, ci)


def verdict(claim: dict[str, Any]) -> str:
    """``pass``, ``FAIL`` or ``n/a`` (not evaluated)."""
    return {True: "pass", False: "FAIL", None: "n/a"}[claim["pass"]]


def report_markdown(results: dict[str, Any]) -> str:
    """The report: claims, per-cell measures, the configuration, software and wall time."""
    config, claims = results["config"], results["claims"]
    worlds, algorithms = _ordered_cells(results)
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
                f"{_with_ci(measure['value'], measure['ci95'])}{mark}"
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
                _with_ci(summary[measure]["mean"], summary[measure]["ci95"])
                for measure in (*MEASURES, "task_return")
            ]
            lines.append(
                f"| {world} | {ALGORITHM_LABELS[algorithm]} | " + " | ".join(values) + " |"
            )
    lines += [
        "",
        f"Obstacle periods: {', '.join(f'{world} {WORLD_PERIODS[world]}' for world in worlds)} "
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
        backend, finished = (
            escape_markdown(timing["backend"]),
            escape_markdown(timing["finished_utc"]),
        )
        lines.append(
            f"Wall time {timing['wall_s']:.1f} s on the {backend} backend with "
            f"{timing['threads']} thread(s): {timing['env_steps']} environment steps, "
            f"{timing['env_steps_per_s']} steps/s (finished {finished})."
        )
    else:
        lines.append("not recorded")
    return "\n".join(lines) + "\n"


def load_results(results_dir: str | os.PathLike) -> dict[str, Any]:
    """The results in ``results_dir/results.json``, checked against the schema (one-line errors)."""
    path = Path(results_dir) / RESULTS_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: run `factorq paper --out {results_dir}`")
    return load_results_file(path)


def write_results(results: dict[str, Any], out_dir: str | os.PathLike) -> dict[str, Path]:
    """Write ``results.json``, ``figure3.png`` and ``report.md`` to ``out_dir``, atomically.

    ``results.json`` is renamed into place first: a results file on disk is always complete, and
    ``factorq report`` can redraw the other two from it.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return _write(results, out, with_results_file=True)


def regenerate(results_dir: str | os.PathLike) -> dict[str, Path]:
    """Rewrite ``figure3.png`` and ``report.md`` in ``results_dir`` from its ``results.json``."""
    return _write(load_results(results_dir), Path(results_dir), with_results_file=False)


def _write(results: dict[str, Any], out: Path, *, with_results_file: bool) -> dict[str, Path]:
    """The files of ``results`` in ``out``, in this order, all atomically."""
    writers: dict[str, tuple[Path, Callable[[Path], Any]]] = {
        "results": (out / RESULTS_FILE, lambda path: path.write_text(dumps(results))),
        "figure": (out / FIGURE_FILE, lambda path: figure3(results, path)),
        "report": (out / REPORT_FILE, lambda path: path.write_text(report_markdown(results))),
    }
    if not with_results_file:
        del writers["results"]
    write_all_atomic(dict(writers.values()))
    return {name: path for name, (path, _) in writers.items()}
