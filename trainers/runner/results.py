"""Result files: JSON written for people and programs (``dumps``: indented, number lists on one
line, non-finite numbers as null), all or nothing (``write_all_atomic``), read back with a clear
error (``read_json``), with what computed them (``software_versions``).

Every results file carries ``"schema_version"`` (``SCHEMA_VERSION``, the layout the tutorials
document); a change that breaks readers raises it, and ``read_json`` refuses a newer file
instead of misreading it (other JSON it reads, such as kept units, has no version).
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable, Iterable
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from factorq_trainers.analysis.stats import finite_or_none
from factorq_trainers.runner import outdir, reading

#: The layout this code reads and writes.
SCHEMA_VERSION = 1
#: The packages whose versions a results file records.
PACKAGES = ("factorq-torch", "torch", "torchrl", "tensordict", "gymnasium", "numpy", "matplotlib")


class FigureError(RuntimeError):
    """Drawing a figure failed (matplotlib's error, in one line); here, below the reports, so that
    the runner's frame can tell it from a bug."""


def new_figure(**options: Any) -> Any:
    """A matplotlib ``Figure(**options)`` on an Agg canvas, as every report draws: no pyplot, so
    no global state and no display (matplotlib is imported here, when a figure is drawn)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(**options)
    FigureCanvasAgg(figure)
    return figure


def dumps(results: dict[str, Any]) -> str:
    """``results`` as JSON: indented, lists of numbers on one line (numpy arrays as lists),
    non-finite numbers as null."""
    return _dumps(results, 0) + "\n"


def _dumps(value: Any, level: int) -> str:
    if isinstance(value, np.ndarray):
        return _dumps(value.tolist(), level)
    if isinstance(value, float | np.floating):
        return json.dumps(finite_or_none(value))
    if isinstance(value, dict):
        if not value:
            return "{}"
        inner = "  " * (level + 1)
        items = [f"{inner}{json.dumps(str(k))}: {_dumps(v, level + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + "  " * level + "}"
    if isinstance(value, list | tuple):
        if not set(map(type, value)) & {dict, list, tuple}:
            try:  # plain finite numbers and texts: json's own, in C
                text = json.dumps(value)
            except TypeError:  # numpy scalars
                text = "NaN"
            if "NaN" not in text and "Infinity" not in text:
                return text
            return "[" + ", ".join(_dumps(item, level) for item in value) + "]"
        inner = "  " * (level + 1)
        items = [f"{inner}{_dumps(item, level + 1)}" for item in value]
        return "[\n" + ",\n".join(items) + "\n" + "  " * level + "]"
    if isinstance(value, np.integer | np.bool_):
        return json.dumps(value.item())
    return json.dumps(value)


def write_atomic(path: str | os.PathLike, write: Callable[[Path], object]) -> None:
    """``write_all_atomic`` of one file: a reader never sees it partial."""
    write_all_atomic({Path(path): write})


def temporary_path(path: Path) -> Path:
    """Where ``write_all_atomic`` writes ``path`` before renaming it: ``.NAME.PID.factorq-tmp``
    beside it (``factorq_trainers.runner.outdir`` removes those of killed writers)."""
    return path.with_name(outdir.temporary_name(path.name))


def write_all_atomic(writers: dict[Path, Callable[[Path], object]]) -> None:
    """Write every file to a temporary next to it, then rename them all into place, in order.

    The slow part (drawing, serialising) happens before any rename, so an interruption leaves
    either all the old files or, but for a few renames' time, all the new ones.
    """
    links = [path for path in writers if path.is_symlink()]
    if links:  # the rename would replace the link, not write through it, but it is not ours
        raise outdir.LinkRefused(links[0])
    temporaries = {path: temporary_path(path) for path in writers}
    try:
        for path, write in writers.items():
            # made new here (never through a link planted at the temporary's name), then filled
            os.close(outdir.create_new(temporaries[path]))
            try:
                write(temporaries[path])
            except OSError as error:  # a full disk, a quota, a file size limit
                raise WriteError(path, error) from None
        for path, temporary in temporaries.items():
            os.replace(temporary, path)
    finally:
        for temporary in temporaries.values():
            temporary.unlink(missing_ok=True)


class WriteError(OSError):
    """A file that could not be written (a full disk, a quota, a file size limit, ...), in one
    line naming it; what was at its place before is kept (every file is written to a temporary
    first). An ``OSError``, as the commands expect of a failed write (their exit 1)."""

    def __init__(self, path: Path, error: BaseException):
        reason = error.strerror if isinstance(error, OSError) and error.strerror else str(error)
        reason = " ".join(str(reason).split())[:200]
        super().__init__(
            getattr(error, "errno", None),
            f"cannot write {path}: {reason} (a full disk, a quota or a file size limit?); what "
            f"was there is kept",
        )
        self.path = path

    def __str__(self) -> str:
        return self.strerror or ""


#: A results file of the default run is about 200 kB; far larger files are not ours.
MAX_FILE_BYTES = 256 * 1024 * 1024


def read_json(path: Path, required: Iterable[str], missing_hint: str) -> dict[str, Any]:
    """The results stored in ``path``; a clear error when it is missing, not a regular file, too
    large or deep (``reading.read_json``), not JSON, lacks one of the ``required`` entries or was
    written by a newer version (``missing_hint``: how to make the file, for the error when it
    does not exist)."""
    try:
        results = reading.read_json(path, "", MAX_FILE_BYTES)
    except reading.FileMissing:
        raise FileNotFoundError(f"{path} does not exist: {missing_hint}") from None
    except reading.ReadError as error:
        raise ValueError(f"{error}: not a results file") from None
    if not isinstance(results, dict):
        raise ValueError(f"{path} is not a results file: it holds no JSON object")
    missing = [key for key in required if key not in results]
    if missing:
        raise ValueError(f"{path} is not a results file: {', '.join(missing)} missing")
    if "schema_version" not in results:  # not a results file: kept units, a sweep's run file
        return results
    version = results["schema_version"]
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise ValueError(f"{path} has schema_version={version!r}: must be a positive integer")
    if version > SCHEMA_VERSION:
        raise ValueError(
            f"{path} has schema_version={version!r}, newer than this factorq reads "
            f"({SCHEMA_VERSION}): update factorq-torch"
        )
    return results


def software_versions() -> dict[str, str]:
    """Versions of python, the libraries that computed the results, and the platform."""
    versions = {"python": platform.python_version()}
    for package in PACKAGES:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    versions["platform"] = platform.platform()
    return versions


#: The paper's body as a results file's config spells it, and how a title names another value
#: (an option a config lacks reads as the paper's: the label names only what differs; a number
#: differs where it is not zero).
PAPER_BODY = {
    "body": ("translate", "{} body"),
    "sensors": ("cross", "{} sensors"),
    "distractors": (0, "{} distractors"),
    "sensor_permutation": (None, "permuted sensors (seed {})"),
    "sensor_noise": (0.0, "sensor noise {}"),
    "actuator_noise": (0.0, "actuator noise {}"),
}


def _shown(value: Any) -> str:
    text = str(value)
    return text if len(text) <= 40 else text[:37] + "..."


def body_label(results: dict[str, Any]) -> str | None:
    """What a results file ran when it is not the paper's body and grid, for titles: e.g.
    ``"heading body, ring sensors, 4 distractors, permuted sensors (seed 3), sensor noise
    0.05"``, or ``"Corridor world (length 12, density 0.4, ...)"`` for another world
    (``results["world"]``); None for the paper's default. Values are shown as they are (a
    results file is untrusted: callers escape for Markdown)."""
    world = results.get("world")
    if isinstance(world, dict):
        options = world.get("config")
        if not isinstance(options, dict):
            options = {}
        described = ", ".join(f"{_shown(k)} {_shown(v)}" for k, v in list(options.items())[:6])
        name = _shown(world.get("name", "another"))
        return f"{name} world ({described})" if described else f"{name} world"
    config = results.get("config")
    if not isinstance(config, dict):
        config = {}
    parts = []
    for name, (default, label) in PAPER_BODY.items():
        value = config.get(name, default)
        if bool(value) if isinstance(default, int | float) else value != default:
            parts.append(label.format(_shown(value)))
    return ", ".join(parts) or None
