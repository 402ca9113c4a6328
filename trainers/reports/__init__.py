"""``factorq report DIR``, without importing torch: ``regenerate`` finds which command wrote
``DIR`` by its results file's name (the registry's ``files["json"]``), checks the file, and
redraws the Markdown and the figure with the command's report module (its folder's ``report.py``,
else its ``command.py``: ``markdown(results)``, ``figure(results, path)``), all at once; a
``factorq sweep`` folder gets its ``sweep.md`` and figures redrawn from ``sweep.json``."""

from __future__ import annotations

import functools
import importlib
import os
from pathlib import Path
from typing import Any

from factorq_trainers.runner import frame, kept, registry, results


def find(results_dir: str | os.PathLike) -> tuple[Any, Path]:
    """The registry entry of the command whose results file is in ``results_dir``, and the
    file (a FileNotFoundError naming the files looked for when none is there)."""
    directory = Path(results_dir)
    entries = registry.commands().values()
    for entry in entries:
        path = directory / entry.files["json"]
        if path.is_file():
            return entry, path
        if path.exists():  # a FIFO, a device, a directory: not "missing"
            raise ValueError(f"{path} is not a regular file: not a results file")
    looked = ", ".join([*(entry.files["json"] for entry in entries), "sweep.json"])
    raise FileNotFoundError(
        f"{directory} holds no results file of a factorq command ({looked}): run one with "
        f"--out {directory}"
    )


def check_results(path: Path, command: str, data: dict[str, Any]) -> None:
    """Refuse (a ValueError naming ``path``) a results file of another command, or whose values
    are impossible (``runner.kept.check_values``: numbers finite, counts whole and >= 0,
    fractions in [0, 1], and the command's report's own ``results_problem``), before anything
    is drawn from it."""
    remedy = f"run `factorq {command}` again to rewrite it"
    if "schema_version" not in data:
        raise ValueError(f"results file {path} has no schema_version: {remedy}")
    if data.get("command", command) != command:
        raise ValueError(
            f"results file {path} was written by command {data.get('command')!r}, not "
            f"`factorq {command}` (whose file name it has): {remedy}"
        )
    report = importlib.import_module(registry.commands()[command].report)
    kept.check_values(path, "results file", data, remedy, getattr(report, "results_problem", None))


def regenerate(results_dir: str | os.PathLike) -> dict[str, Path]:
    """Rewrite the Markdown and the figure in ``results_dir`` from its results file."""
    try:
        entry, path = find(results_dir)
    except FileNotFoundError:
        from factorq_trainers.reports import sweep

        if not (Path(results_dir) / sweep.JSON_FILE).exists():
            raise
        return sweep.regenerate(results_dir)  # factorq sweep's --out
    report = importlib.import_module(entry.report)
    data = results.read_json(path, ("config",), f"run `factorq {entry.name}`")
    check_results(path, entry.name, data)
    draw = functools.partial(report.figure, data) if hasattr(report, "figure") else None
    return frame.write_report(report, data, Path(results_dir), entry.files, draw)
