"""``factorq sweep``'s files from its ``sweep.json`` dict alone (no torch): ``sweep.md``, one
row per configuration and cell, and ``sweep-<axis>.png`` per swept axis."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from factorq_trainers.analysis import claims, stats
from factorq_trainers.runner import results as result_files

JSON_FILE = "sweep.json"
REPORT_FILE = "sweep.md"
MEASURE_LABELS = {
    **claims.MEASURE_LABELS,
    "steps_to_threshold": "steps to threshold",
    "avoidable_greedy_collisions": "avoidable greedy collisions",
    "fraction_right_within_target": "right structure within target",
    "collisions_vs_oracle": "collisions vs oracle",
}


def _shown(value: Any) -> str:
    return ",".join(map(str, value)) if isinstance(value, list | tuple) else str(value)


def _label(measure: str) -> str:
    return MEASURE_LABELS.get(measure, measure.replace("_", " "))


def report_markdown(sweep: dict[str, Any]) -> str:
    """``sweep.md``: one row per configuration and cell, means with 95% intervals."""
    axes = sweep["axes"]
    measures = list(sweep.get("measures", claims.MEASURES))  # the paper's, unless named
    is_paper = sweep.get("command", "paper") == "paper"
    per = "Per run" if is_paper else "Per experiment"
    claims_column = ["claims passed"] if is_paper else []
    lines = [
        f"# factorq sweep ({sweep.get('command', 'paper')})",
        "",
        f"{len(sweep['configurations'])} configurations x {sweep['seeds']} seeds "
        "(one task per configuration); base: "
        + (", ".join(f"{k}={_shown(v)}" for k, v in sweep["base"].items()) or "defaults")
        + f"; computed {sweep['timing']['where']}. {per}: means over seeds [95% interval].",
        "",
        "| " + " | ".join([*axes, "world", "algorithm", *map(_label, measures),
                          *claims_column]) + " |",
        "| " + " | ".join(["---"] * (len(axes) + 2)
                          + ["---:"] * (len(measures) + len(claims_column))) + " |",
    ]  # fmt: skip
    for row in sweep["configurations"]:
        evaluated = [claim for claim in row["claims"].values() if claim["pass"] is not None]
        passed = f"{sum(c['pass'] for c in evaluated)}/{len(evaluated)}" if evaluated else "n/a"
        passed_column = [passed] if is_paper else []
        for cell in row["cells"].values():
            numbers = [stats.with_ci(cell[m]["mean"], cell[m]["ci95"]) for m in measures]
            values = [_shown(row["values"].get(axis, "")) for axis in axes]
            lines.append(
                "| "
                + " | ".join([*values, cell["world"], cell["algorithm"], *numbers, *passed_column])
                + " |"
            )
    lines.append("")
    return "\n".join(lines)


def write_axis_figure(sweep: dict[str, Any], axis: str, path: Path) -> None:
    """Means with 95% intervals of the three measures against ``axis``, one line per world and
    algorithm; the other axes held at their first value (named in the title)."""
    others = {
        name: sweep["configurations"][0]["values"].get(name)
        for name in sweep["axes"]
        if name != axis
    }
    rows = [
        row
        for row in sweep["configurations"]
        if axis in row["values"]
        and all(row["values"].get(name) == value for name, value in others.items())
    ]
    labels = [_shown(row["values"][axis]) for row in rows]
    numeric = all(isinstance(row["values"][axis], int | float) for row in rows)
    x = np.array([row["values"][axis] for row in rows], float) if numeric else np.arange(len(rows))
    measures = list(sweep.get("measures", claims.MEASURES))
    figure = result_files.new_figure(figsize=(13, 4), layout="constrained")
    panels = figure.subplots(1, len(measures))
    cells = list(dict.fromkeys(cell for row in rows for cell in row["cells"]))  # e.g. worlds axis
    for panel, measure in zip(panels, measures, strict=True):
        for cell in cells:
            entries = [row["cells"].get(cell, {}).get(measure) for row in rows]
            mean = np.array([np.nan if e is None else e["mean"] for e in entries], float)
            bounds = [[m, m] if e is None or e["ci95"] is None else e["ci95"]
                      for m, e in zip(mean, entries, strict=True)]  # fmt: skip
            low, high = np.array(bounds, float).reshape(-1, 2).T
            errors = np.stack([np.maximum(mean - low, 0), np.maximum(high - mean, 0)])
            panel.errorbar(x, mean, yerr=errors, marker="o", capsize=3, label=cell)
        panel.set_xlabel(axis)
        per = " per run" if sweep.get("command", "paper") == "paper" else ""
        panel.set_ylabel(f"{_label(measure)}{per}")
        if measure in ("collisions", "greedy_collisions", "avoidable_greedy_collisions"):
            panel.set_yscale("symlog", linthresh=1.0)
        if not numeric:
            panel.set_xticks(x, labels)
    if cells:
        panels[0].legend(fontsize="small")
    held = ", ".join(f"{k}={_shown(v)}" for k, v in others.items())
    figure.suptitle(
        f"{axis}: means over {sweep['seeds']} seeds, 95% intervals"
        + (f" ({held})" if held else ""),
        fontsize="medium",
    )
    figure.savefig(path, dpi=100, format="png")


def write_outputs(
    sweep: dict[str, Any], out: str | os.PathLike[Any], json: bool = True
) -> dict[str, Path]:
    """``sweep.json`` (unless not ``json``), ``sweep.md`` and ``sweep-<axis>.png`` per axis, all
    written atomically."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    writers: dict[Path, Callable[[Path], object]] = {}
    if json:
        writers[out / JSON_FILE] = lambda path: path.write_text(result_files.dumps(sweep))
    writers[out / REPORT_FILE] = lambda path: path.write_text(report_markdown(sweep))
    for axis in sweep["axes"]:
        writers[out / f"sweep-{axis}.png"] = functools.partial(write_axis_figure, sweep, axis)
    result_files.write_all_atomic(writers)
    return {path.name: path for path in writers}


#: The entries ``factorq report`` needs in a ``sweep.json``.
REQUIRED = ("axes", "configurations", "seeds", "base", "timing")


def regenerate(out: str | os.PathLike[Any]) -> dict[str, Path]:
    """``factorq report`` on a sweep's ``--out``: ``sweep.md`` and the figures redrawn from
    ``sweep.json`` alone (the JSON itself is left as it is)."""
    sweep = result_files.read_json(Path(out) / JSON_FILE, REQUIRED, "run `factorq sweep`")
    return write_outputs(sweep, out, json=False)
