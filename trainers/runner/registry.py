"""The commands of ``factorq``: every folder ``trainers/commands/<name>/`` whose ``command.py``
assigns ``NAME = "<name>"`` is one. ``NAME``, ``HELP`` (default: the first line of the module's
docstring), ``FILES`` and ``FIGURE_PROCESS`` are read from the source with ``ast``, so listing
the commands imports none of them (nor torch); ``load`` imports the one being run.
"""

from __future__ import annotations

import ast
import functools
import importlib
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

PACKAGE = "factorq_trainers.commands"
#: The commands that are not experiments: ``report`` redraws files, ``sweep`` runs grids of
#: another command's configurations.
BUILT_IN = ("report", "sweep")


class Entry(NamedTuple):
    """A registered command: its name, its module's dotted name, its one-line help, its files
    (``FILES``, else ``NAME.json/.md/.png``), the module of its report (its folder's
    ``report.py``, else the command's own) and whether its figure is drawn by a helper process
    started before torch loads (``FIGURE_PROCESS = True``: its folder's ``figure_process.py``
    provides ``FigureProcess``, its report ``send_figure``)."""

    name: str
    module: str
    help: str
    files: dict[str, str]
    report: str
    figure_process: bool = False


def _constant(tree: ast.Module, name: str, kind: type = str) -> Any:
    """The literal (a ``kind``: a string, a dict of strings) assigned to ``name`` at the top level
    of ``tree`` (None if none)."""
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == name for t in node.targets
        ):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                return None
            return value if isinstance(value, kind) else None
    return None


def default_files(name: str) -> dict[str, str]:
    """A command's files unless it declares ``FILES``: ``NAME.json``, ``NAME.md``, ``NAME.png``."""
    return {"json": f"{name}.json", "report": f"{name}.md", "figure": f"{name}.png"}


@functools.cache
def commands() -> dict[str, Entry]:
    """Every registered command by name, in file-name order."""
    folder = Path(__file__).resolve().parent.parent / "commands"
    found: dict[str, Entry] = {}
    for path in sorted(folder.glob("*/command.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        name, folder_name = _constant(tree, "NAME"), path.parent.name
        if name != folder_name:
            raise RuntimeError(f"{path}: NAME is {name!r}, not its folder's name {folder_name!r}")
        if name in BUILT_IN:
            raise RuntimeError(f"{path}: {name!r} is a built-in command")
        docstring = (ast.get_docstring(tree) or name).strip().splitlines()[0]
        help_text = _constant(tree, "HELP") or docstring
        package = f"{PACKAGE}.{name}"
        files = {**default_files(name), **(_constant(tree, "FILES", dict) or {})}
        has_report = (path.parent / "report.py").is_file()
        report = f"{package}.report" if has_report else f"{package}.command"
        figure_process = _constant(tree, "FIGURE_PROCESS", bool) is True
        found[name] = Entry(name, f"{package}.command", help_text, files, report, figure_process)
    return found


def load(name: str) -> ModuleType:
    """The module of command ``name`` (imported now)."""
    try:
        entry = commands()[name]
    except KeyError:
        raise ValueError(
            f"{name!r} is not a factorq command: choose one of {', '.join(commands())}"
        ) from None
    return importlib.import_module(entry.module)
