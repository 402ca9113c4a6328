"""The paper's Figure 3, drawn with matplotlib from a results dict: nothing here imports torch.

``report.figure3`` (beside it) draws it in the calling process; ``factorq paper`` draws it in
``figure_process``'s helper process, which loads matplotlib while the main process loads torch. Both
call ``draw`` with the same arguments, so the file is the same byte for byte."""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np

from factorq_trainers.analysis.vocabulary import among, label
from factorq_trainers.runner.results import body_label, new_figure

COLOURS = {"q-learning": "#D55E00", "factor-q": "#0072B2"}  # colour-blind safe (Okabe-Ito)
# Greedy collisions: a darker shade of the algorithm's colour, dashed, drawn over all collisions
# (for Q-learning the two nearly coincide, and the dashes must stay visible).
GREEDY_COLOURS = {"q-learning": "#7A3500", "factor-q": "#003A5C"}
WORLD_TITLES = {
    "static": "static world",
    "semi-dynamic": "semi-dynamic world (obstacles move every 10 steps)",
    "dynamic": "dynamic world (obstacles move every step)",
}


def preload() -> None:
    """Import matplotlib's modules that ``draw`` uses (about 0.4 s)."""
    import matplotlib.backends.backend_agg
    import matplotlib.figure
    import matplotlib.lines
    import matplotlib.ticker  # noqa: F401


class Frame(NamedTuple):
    """A figure with everything but the curves (``frame``): its ``spec``, the figure, its axes
    ``[2, worlds]``, and the collision axis' linear threshold."""

    spec: tuple
    figure: Any
    axes: Any
    resolution: float


def frame_spec(results: dict[str, Any], worlds: Sequence[str], algorithms: Sequence[str]) -> tuple:
    """What the frame of ``draw(results, ...)`` depends on (not the cells): equal specs, equal
    frames."""
    config = results["config"]
    body = body_label(results)
    if results.get("world") is not None:  # another world than the grid: its name and options
        where = body
    else:
        where = f"{config['size']}\u00d7{config['size']} grid with {config['obstacles']} obstacles"
        where += f", {body}" if body else ""
    title = (
        f"Q-learning vs Factor-Q, {where}\n"
        f"mean of {config['seeds']} seeds \u00d7 {config['runs']} runs per episode, "
        "95% confidence bands across seeds"
    )
    legend = tuple((name, label(name)) for name in algorithms)
    return (tuple(worlds), legend, config["seeds"], config["runs"], config["episodes"], title)


def frame(spec: tuple) -> Frame:
    """The figure of ``spec`` (``frame_spec``) without its curves: axes, scales, titles, labels,
    legend. ``draw`` adds the curves and saves it."""
    from matplotlib.lines import Line2D
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    worlds, legend, seeds, runs, episodes, title = spec
    plain = FuncFormatter(lambda value, _: f"{value:g}")  # 0.01, 1, 300 rather than 10^-2, 3x10^2
    width, height = max(4.4 * len(worlds) + 0.6, 6.0), 7.4
    figure = new_figure(figsize=(width, height), dpi=150)
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
    resolution = 1.0 / (seeds * runs)
    for column, world in enumerate(worlds):
        steps_axis, collisions_axis = axes[0, column], axes[1, column]
        # y given: matplotlib then skips placing the title around tick labels (there are none
        # above the axes), a fifth of the figure's drawing time
        steps_axis.set_title(WORLD_TITLES[world], fontsize=11, y=1.0, pad=6.0)
        steps_axis.set_yscale("log")
        steps_axis.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 3.0, 5.0)))
        collisions_axis.set_yscale("symlog", linthresh=resolution, linscale=0.5)
        collisions_axis.set_xlabel("episode")
        for axis in (steps_axis, collisions_axis):
            axis.grid(True, which="major", alpha=0.3)
            axis.set_xlim(1, episodes)
            axis.yaxis.set_major_formatter(plain)
            axis.yaxis.set_minor_formatter(NullFormatter())
    axes[0, 0].set_ylabel("steps per episode (log)")
    axes[1, 0].set_ylabel("collisions per episode (log)")
    handles = [Line2D([], [], color=COLOURS[name], lw=2, label=label) for name, label in legend]
    handles += [
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
    figure.suptitle(title, fontsize=11, y=1 - 0.08 / height, va="top")
    return Frame(spec, figure, axes, resolution)


def draw(
    results: dict[str, Any],
    path: str | os.PathLike | io.BytesIO,
    worlds: Sequence[str],
    algorithms: Sequence[str],
    *,
    prepared: Frame | None = None,
) -> None:
    """Draw the paper's Figure 3 from ``results`` and save it as a PNG at ``path``.

    ``worlds`` and ``algorithms`` are the cells present, in the order drawn (the legend names the
    algorithms by their labels, ``analysis.vocabulary``'s). Columns are worlds; the top row shows
    steps per episode, the bottom row collisions per episode (solid: all, dashed: greedy) on a log
    scale, each the mean over seeds and runs with its 95% confidence band across seeds. Reads
    ``results["config"]``, ``results.get("world")`` and each cell's ``curves``, ``curves_ci_low``
    and ``curves_ci_high``. ``prepared``: a ``frame`` made (and drawn) beforehand, used if its spec
    is this figure's (the same bytes, less work now).
    """
    spec = frame_spec(results, worlds, algorithms)
    figure, axes, resolution = (prepared if prepared and prepared.spec == spec else frame(spec))[1:]
    highest = 0.0
    for column, world in enumerate(worlds):
        steps_axis, collisions_axis = axes[0, column], axes[1, column]
        for algorithm in algorithms:
            cell = results["cells"][f"{world}/{algorithm}"]
            colour = COLOURS[algorithm]
            _curve(steps_axis, cell, "steps", colour, "-", 1.6, alpha=0.25)
            _curve(collisions_axis, cell, "collisions", colour, "-", 1.6, alpha=0.25)
            greedy = GREEDY_COLOURS[algorithm]
            _curve(collisions_axis, cell, "greedy_collisions", greedy, "--", 1.1, alpha=0.12)
            highest = max(highest, max(cell["curves"]["collisions"]))
    axes[1, 0].set_ylim(0, max(highest, resolution) * 1.5)  # the row shares its y axis
    # zlib level 1: a slightly larger file, encoded several times faster.
    figure.savefig(path, format="png", dpi=150, pil_kwargs={"compress_level": 1})


def _curve(
    axis: Any, cell: dict[str, Any], name: str, colour: str, style: str, width: float, alpha: float
) -> None:
    mean = np.asarray(cell["curves"][name], dtype=np.float64)
    episodes = np.arange(1, mean.size + 1)
    axis.plot(episodes, mean, color=colour, ls=style, lw=width, zorder=3 if style == "--" else 2)
    low, high = cell["curves_ci_low"][name], cell["curves_ci_high"][name]
    if low is not None:
        low = np.maximum(np.asarray(low, dtype=np.float64), 0.0)  # counts are never negative
        axis.fill_between(episodes, low, high, color=colour, alpha=alpha, lw=0)


#: The entries of a cell that ``draw`` reads.
CURVE_ENTRIES = ("curves", "curves_ci_low", "curves_ci_high")


def drawn_part(results: dict[str, Any]) -> dict[str, Any]:
    """What ``draw`` reads of ``results`` (the config, the world, each cell's curves): the message
    that the helper process is sent, much smaller than the results."""
    return {
        "config": results["config"],
        "world": results.get("world"),
        "cells": {
            key: {entry: cell[entry] for entry in CURVE_ENTRIES}
            for key, cell in results["cells"].items()
        },
    }


#: ``factorq paper``'s defaults as ``draw`` reads them (``tests/test_figure_process.py`` checks
#: them against ``PaperConfig``): the figure the helper process prepares before it is sent one.
DEFAULT_CONFIG = {"seeds": 100, "runs": 10, "episodes": 200, "size": 10, "obstacles": 10}
DEFAULT_CELLS = (tuple(WORLD_TITLES), among("q-learning", "factor-q"))


def default_spec() -> tuple:
    """The ``frame_spec`` of ``factorq paper`` with its defaults."""
    return frame_spec({"config": DEFAULT_CONFIG}, *DEFAULT_CELLS)


def prepare(spec: tuple) -> Frame:
    """The ``frame`` of ``spec``, drawn once: its ticks, texts and layout exist, and ``draw`` with
    data of that spec then only adds and draws the curves (a quarter less work than from scratch,
    the same bytes)."""
    prepared = frame(spec)
    prepared.figure.canvas.draw()
    return prepared


def warm_up() -> None:
    """Draw a made-up figure of the default run's shape into memory, then drop it: what loads
    lazily (a third of a first figure's time) is then loaded (``figure_process``)."""
    decay = np.exp(-np.arange(DEFAULT_CONFIG["episodes"]) / 20.0)
    cells = {}
    worlds, algorithms = DEFAULT_CELLS
    for world in worlds:
        for scale, algorithm in zip((1.0, 0.02), algorithms, strict=True):
            curves = {
                "steps": (300 * decay + 20).tolist(),
                "collisions": (scale * (40 * decay + 2)).tolist(),
                "greedy_collisions": (scale * (20 * decay + 1)).tolist(),
            }
            cells[f"{world}/{algorithm}"] = {
                "curves": curves,
                "curves_ci_low": {k: (np.asarray(v) * 0.9).tolist() for k, v in curves.items()},
                "curves_ci_high": {k: (np.asarray(v) * 1.1).tolist() for k, v in curves.items()},
            }
    results = {"config": DEFAULT_CONFIG, "cells": cells}
    draw(results, io.BytesIO(), *DEFAULT_CELLS, prepared=prepare(default_spec()))
