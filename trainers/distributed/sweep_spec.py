"""A sweep's spec (``factorq sweep``): the sweep file and options read, checked and expanded into
the configurations of one command, before anything runs or is written.

A sweep file (every key optional but the axes; options given on the command line win)::

    seeds = 100              # per configuration
    out = "results/sweep"

    [base]                   # fields every configuration shares
    episodes = 100

    [grid]                   # the cartesian product of these axes ...
    obstacles = [5, 10, 20]
    eta = [0.05, 0.1, 0.2]

    [[configs]]              # ... crossed with this list (each entry one configuration)
    size = 8

Any field of the command's config (``PaperConfig`` by default; ``command = "compare"``, or any
other registered command, for that command's) is an axis or a base value, but for ``seeds`` and
``out``, which the sweep sets: the fields are read from the dataclass, so new ones are sweepable
without edits here. Unknown fields and invalid values are refused before anything is written.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib
import itertools
import json
import math
import sys
import types
import typing
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from factorq_torch.base.validation import INT32_MAX, check_int
from factorq_trainers.runner import kept, outdir, reading, registry
from factorq_trainers.runner.frame import plain

DEFAULT_SEEDS = 100
DEFAULT_OUT = "results/sweep"
SPEC_KEYS = ("command", "seeds", "out", "base", "grid", "configs")
#: Where a sweep keeps each finished configuration's results dict.
CONFIGS_DIRECTORY = "configs"


class SweepError(ValueError):
    """A sweep spec or value that cannot be used; the message says which and why."""


def check_command(command: Any, source: str = "sweep file") -> str:
    """``command`` if a sweep can run its configs, else a ``SweepError`` saying which can."""
    names = tuple(registry.commands())  # a tuple: an unhashable command is simply not in it
    if command not in names:
        raise SweepError(f"{source}: command={command!r} is not one of {', '.join(names)}")
    reports = _reports_of(command)
    if not (hasattr(reports, "sweep_cells") and hasattr(reports, "SWEEP_MEASURES")):
        raise SweepError(
            f"{source}: command={command!r} cannot be swept: {reports.__name__} declares no "
            f"sweep_cells and SWEEP_MEASURES (what a sweep reports per configuration)"
        )
    return command


def _reports_of(command: str) -> Any:
    """The report module of ``command`` (its ``sweep_cells`` and ``SWEEP_MEASURES``)."""
    return importlib.import_module(registry.commands()[command].report)


def config_class(command: str = "paper") -> type:
    """The config dataclass of ``command`` (``PaperConfig``, ``CompareConfig``, ...)."""
    return registry.load(command).CONFIG


def reserved_fields(command: str = "paper") -> tuple[str, ...]:
    """The fields of ``command``'s config that the sweep sets itself: ``seeds`` and ``out``, or
    what the module of its config declares in ``SWEEP_RESERVED`` (compare adds its ``logger``)."""
    module = sys.modules[config_class(command).__module__]
    return tuple(getattr(module, "SWEEP_RESERVED", ("seeds", "out")))


def nested_fields(command: str = "paper") -> list[str]:
    """The fields of ``command``'s config that are configs themselves: not sweepable."""
    hints = typing.get_type_hints(config_class(command))
    return [name for name, hint in hints.items() if dataclasses.is_dataclass(hint)]


def sweepable_fields(command: str = "paper") -> dict[str, Any]:
    """Field name -> type annotation of every field of ``command``'s config a sweep may set
    (nested configs and the sweep's own fields left out)."""
    kind = config_class(command)
    hints = typing.get_type_hints(kind)
    skipped = {*reserved_fields(command), *nested_fields(command)}
    return {f.name: hints[f.name] for f in fields(kind) if f.name not in skipped}


def config_digest(config: Any) -> str:
    """A short hash of the fields that decide ``config``'s numbers: every field but those the
    module of its config declares in ``DIGEST_IGNORED`` (default ``out`` and ``threads``;
    ``compare`` also leaves out its ``logger``, ``paper`` its backend, device and
    ``shard_seeds``: the numbers are the same bit for bit)."""
    module = sys.modules[type(config).__module__]
    values = plain(config)
    ignored = getattr(module, "DIGEST_IGNORED", ("out", "threads"))
    relevant = {key: value for key, value in values.items() if key not in ignored}
    return hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()[:16]


def _plain(value: Any) -> Any:
    """TOML lists as tuples (the configs' sequence fields), everything else as is."""
    return tuple(value) if isinstance(value, list) else value


@dataclass(frozen=True)
class SweepSpec:
    """A sweep of ``command``'s configs: the fields every configuration shares (``base``, (name,
    value) pairs), the swept axes (``grid``, (name, values) pairs: their cartesian product)
    crossed with explicit configurations (``configs``), ``seeds`` of every configuration, and
    ``out``, the directory of sweep.json, sweep.md, the figures and configs/."""

    base: tuple[tuple[str, Any], ...] = ()
    grid: tuple[tuple[str, tuple[Any, ...]], ...] = ()
    configs: tuple[tuple[tuple[str, Any], ...], ...] = ((),)
    seeds: int = DEFAULT_SEEDS
    out: str = DEFAULT_OUT
    command: str = "paper"

    def __post_init__(self) -> None:
        check_command(self.command, "sweep")
        check_int("seeds", self.seeds, 1, INT32_MAX)
        object.__setattr__(self, "out", outdir.checked_out(self.out, SweepError))
        known = sweepable_fields(self.command)
        reserved, nested = reserved_fields(self.command), nested_fields(self.command)
        entries = [("base", name, (value,)) for name, value in self.base]
        entries += [("grid", name, values) for name, values in self.grid]
        entries += [("configs", name, (value,)) for entry in self.configs for name, value in entry]
        for where, name, values in entries:
            if name in nested:
                raise SweepError(
                    f"field {name!r} in {where} is a nested config of {self.command}'s "
                    f"({', '.join(nested)}): not sweepable; sweepable: {', '.join(known)}"
                )
            if name not in known:
                hint = " (the sweep sets it: a top-level key)" if name in reserved else ""
                raise SweepError(
                    f"unknown field {name!r} in {where}{hint}; sweepable: {', '.join(known)}"
                )
            if where == "grid" and (not isinstance(values, tuple) or not values):
                raise SweepError(f"grid axis {name!r} needs a non-empty list of values")
            if len(set(map(repr, values))) != len(values):
                raise SweepError(f"grid axis {name!r} repeats a value: {list(values)}")
            for value in values:
                try:  # a value, or a list of values (a table would reach no field's check)
                    hash(value)
                except TypeError:
                    raise SweepError(
                        f"field {name!r} in {where} holds {kept.short(value)}: a table is not a "
                        f"value (give a value or a list of values)"
                    ) from None
        count = len(self.configs) * math.prod(len(values) for _, values in self.grid)
        if count > MAX_CONFIGURATIONS:  # from the axes' lengths: nothing expanded yet
            sizes = " x ".join(str(len(values)) for _, values in self.grid) or "1"
            raise SweepError(
                f"the sweep has {count} configurations ({len(self.configs)} configs x grid "
                f"{sizes}), more than {MAX_CONFIGURATIONS}: split it into several sweeps"
            )
        axes = {name for name, _ in self.grid}
        for entry in self.configs:
            clash = axes & {name for name, _ in entry}
            if clash:
                raise SweepError(f"{', '.join(sorted(clash))} is both a grid axis and in configs")
        seen: dict[str, int] = {}
        for index, config in enumerate(self.configurations()):
            key = config_digest(config)
            if key in seen:
                points = self.points()
                first, again = (
                    ", ".join(f"{k}={v!r}" for k, v in points[i].items()) or "base"
                    for i in (seen[key], index)
                )
                raise SweepError(
                    f"configurations {seen[key]} ({first}) and {index} ({again}) are the same "
                    f"configuration: give each once"
                )
            seen[key] = index

    @property
    def axes(self) -> list[str]:
        """The names that vary between configurations, in the order given."""
        names = [name for name, _ in self.grid]
        for entry in self.configs:
            names += [name for name, _ in entry if name not in names]
        return names

    def points(self) -> list[dict[str, Any]]:
        """Each configuration's values of the axes."""
        names = [name for name, _ in self.grid]
        grid = [
            dict(zip(names, values, strict=True))
            for values in itertools.product(*(values for _, values in self.grid))
        ]
        return [{**dict(entry), **point} for entry in self.configs for point in grid]

    @functools.cache  # noqa: B019 - the spec is frozen and small
    def configurations(self) -> list[Any]:
        """The validated config of every point (a ``SweepError`` names the point and the
        value)."""
        kind = config_class(self.command)
        configs = []
        for index, point in enumerate(self.points()):
            values = {**dict(self.base), **point, "seeds": self.seeds, "out": self.out}
            try:
                configs.append(kind(**{k: _plain(v) for k, v in values.items()}))
            except (ValueError, TypeError) as error:
                shown = ", ".join(f"{k}={v!r}" for k, v in point.items()) or "base"
                raise SweepError(f"configuration {index} ({shown}): {error}") from None
        return configs


def checked_document(data: Any, source: str = "sweep file") -> dict[str, Any]:
    """``data``, a parsed sweep file, once its keys and tables are checked (its command is not:
    an option may replace it)."""
    if not isinstance(data, dict):
        raise SweepError(f"{source}: expected a table of keys, got {type(data).__name__}")
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise SweepError(
            f"{source}: unknown key(s) {', '.join(map(repr, unknown))}; known: "
            f"{', '.join(SPEC_KEYS)}"
        )
    for key in ("base", "grid"):
        if not isinstance(data.get(key, {}), dict):
            raise SweepError(f"{source}: [{key}] must be a table")
    configs = data.get("configs", [{}])
    if (
        not isinstance(configs, list)
        or not configs
        or not all(isinstance(c, dict) for c in configs)
    ):
        raise SweepError(f"{source}: configs must be a non-empty array of tables ([[configs]])")
    return data


def spec_from_mapping(data: Any, source: str = "sweep file") -> SweepSpec:
    """A ``SweepSpec`` from a parsed TOML (or YAML) document."""
    data = checked_document(data, source)
    command = check_command(data.get("command", "paper"), source)
    grid = []
    for name, values in data.get("grid", {}).items():
        if not isinstance(values, list):
            raise SweepError(f"{source}: grid axis {name!r} must be a list, got {values!r}")
        grid.append((name, tuple(_plain(value) for value in values)))
    extra = {key: data[key] for key in ("seeds", "out") if key in data}
    try:
        return SweepSpec(
            base=tuple((k, _plain(v)) for k, v in data.get("base", {}).items()),
            grid=tuple(grid),
            configs=tuple(
                tuple((k, _plain(v)) for k, v in entry.items())
                for entry in data.get("configs", [{}])
            ),
            command=command,
            **extra,
        )
    except (ValueError, TypeError) as error:
        raise SweepError(f"{source}: {error}") from None


#: A sweep file is a few hundred bytes; far larger ones are not sweep files.
MAX_SPEC_BYTES = 1024 * 1024
#: Configurations one sweep may hold (each is a whole run): checked from the axes' lengths
#: before anything is expanded (expanding 10**9 points would end in MemoryError, 10**5 in
#: minutes of silence).
MAX_CONFIGURATIONS = 10_000


def read_spec_file(path: str | Path) -> dict[str, Any]:
    """The document of a ``.toml`` sweep file (or ``.yaml``/``.yml`` where PyYAML is installed),
    read by ``reading``: a regular file, bounded in size and nesting before it is parsed, YAML
    without aliases."""
    path = Path(path)
    try:
        if path.suffix in (".yaml", ".yml"):
            try:
                import yaml  # noqa: F401 - only to say what is missing
            except ImportError:
                raise SweepError(
                    f"{path}: YAML needs PyYAML (pip install pyyaml); or use TOML"
                ) from None
            data = reading.read_yaml(path, "sweep file", MAX_SPEC_BYTES)
        else:
            data = reading.read_toml(path, "sweep file", MAX_SPEC_BYTES)
    except reading.ReadError as error:
        raise SweepError(str(error)) from None
    return {} if data is None else data


def parse_value(name: str, text: str, command: str = "paper") -> Any:
    """An option's ``text`` as the type of field ``name`` of ``command``'s config (tuples:
    comma-separated)."""
    known = sweepable_fields(command)
    annotation = known.get(name)
    if annotation is None:
        raise SweepError(f"unknown field {name!r}; sweepable: {', '.join(known)}")
    if isinstance(annotation, types.UnionType):  # int | None -> int
        annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
    if typing.get_origin(annotation) is tuple:
        return tuple(item for item in text.split(",") if item)
    if annotation is bool:
        if text.lower() not in ("true", "false"):
            raise SweepError(f"{name}={text!r} is not true or false")
        return text.lower() == "true"
    if annotation in (int, float):
        try:
            return annotation(text)
        except ValueError:
            raise SweepError(f"{name}={text!r} is not {annotation.__name__}") from None
    return text
