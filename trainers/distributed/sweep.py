"""``factorq sweep``: a grid (or list) of paper configurations, each with its seeds, run as shards
in-process or on a Dask cluster, gathered into ``sweep.json``, ``sweep.md`` and one figure per
swept axis. With ``command = "compare"``, a grid of ``factorq compare`` configurations instead,
each run whole (one task per method) and kept in ``OUT/configs/<digest>.json``
(``run_compare_sweep``); with ``command = "dependencies"``, of ``factorq dependencies``
configurations, one task each (``run_units_sweep``).

    spec (TOML file and/or options) -> configurations -> shards (contiguous seed ranges)
         -> executor (in-process or Dask) -> one .npz per shard, written as it finishes
         -> per configuration: concatenate -> paper.summarise -> sweep.json / sweep.md / figures

A sweep file (every key optional but the axes; options given on the command line win)::

    seeds = 100              # per configuration
    shard_seeds = 25         # seeds per shard: the unit of work, of files and of resumption
    out = "results/sweep"

    [base]                   # fields every configuration shares
    episodes = 100

    [grid]                   # the cartesian product of these axes ...
    obstacles = [5, 10, 20]
    eta = [0.05, 0.1, 0.2]

    [[configs]]              # ... crossed with this list (each entry one configuration)
    size = 8

Any field of ``PaperConfig`` is an axis or a base value, but for ``seeds``, ``first_seed`` and
``out``, which the sweep sets: the fields are read from the dataclass, so new ones are sweepable
without edits here. Unknown fields and invalid values are refused before anything is written.

**Resumption.** Shard files live in ``OUT/shards/<digest>/<first>-<stop>.npz``, where the digest
hashes the fields that decide the numbers. A shard whose file exists is not run again, so a
killed sweep continues where it stopped, and a sweep that adds seeds or axis values runs only the
new shards.

**Identical results.** A shard's numbers depend on its configuration and seed range alone (see
``factorq_trainers.distributed.shards``), so the per-experiment numbers and every summary are the
same in-process, on any number of workers, and after any number of interruptions.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import hashlib
import itertools
import json
import math
import os
import re
import sys
import time
import tomllib
import types
import typing
from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import torch

from factorq_torch.base.validation import INT32_MAX, check_int
from factorq_trainers.analysis import claims, stats
from factorq_trainers.distributed import cluster, shards
from factorq_trainers.experiments import paper
from factorq_trainers.reports import sweep as sweep_report
from factorq_trainers.runner import outdir, resources
from factorq_trainers.runner import results as result_files
from factorq_trainers.runner.frame import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE, Parser

HELP = "run a grid of paper configurations as shards, in-process or on a Dask cluster"
SHARDS_DIRECTORY = "shards"
DEFAULT_SEEDS = 100
DEFAULT_SHARD_SEEDS = 25
DEFAULT_PAPER_SHARD_SEEDS = 10
DEFAULT_OUT = "results/sweep"
#: Fields the sweep sets itself: neither axes nor base values.
RESERVED = ("seeds", "first_seed", "out")
SPEC_KEYS = ("command", "seeds", "shard_seeds", "out", "base", "grid", "configs")
MEASURES = claims.MEASURES  # a paper sweep reports the paper's measures
#: The commands whose configs a sweep runs by their own rules (``command = "..."`` in a sweep
#: file, ``--command``); every other registered command runs each configuration whole, one task
#: each (``run_units_sweep``).
SPECIAL = ("paper", "compare")
#: ``CompareConfig`` fields the sweep sets itself (``logger``: a sweep writes no per-episode logs).
COMPARE_RESERVED = ("seeds", "out", "logger")
#: The fields of another command's config that the sweep sets itself.
UNITS_RESERVED = ("seeds", "out")
#: What a compare sweep reports per method and world (``compare.summarise``'s measures).
COMPARE_MEASURES = ("steps_to_threshold", "collisions", "greedy_collisions")
#: Where a compare sweep keeps each finished configuration's ``comparison.json`` dict.
CONFIGS_DIRECTORY = "configs"


class SweepError(ValueError):
    """A sweep spec or value that cannot be used; the message says which and why."""


def commands() -> tuple[str, ...]:
    """Every command a sweep can run: ``paper``, ``compare`` and each registered command."""
    from factorq_trainers.runner import registry

    return (*SPECIAL, *(name for name in registry.commands() if name not in SPECIAL))


def check_command(command: Any, source: str = "sweep file") -> str:
    """``command`` if a sweep can run its configs, else a ``SweepError`` saying which can."""
    if command not in commands():
        raise SweepError(f"{source}: command={command!r} is not one of {', '.join(commands())}")
    if command not in SPECIAL:
        reports = _reports_of(command)
        if not (hasattr(reports, "sweep_cells") and hasattr(reports, "SWEEP_MEASURES")):
            raise SweepError(
                f"{source}: command={command!r} cannot be swept: {reports.__name__} declares no "
                f"sweep_cells and SWEEP_MEASURES (what a sweep reports per configuration)"
            )
    return command


def _reports_of(command: str) -> Any:
    """The report module of ``command`` (its ``sweep_cells`` and ``SWEEP_MEASURES``)."""
    import importlib

    from factorq_trainers.runner import registry

    return importlib.import_module(registry.commands()[command].report)


def config_class(command: str = "paper") -> type:
    """The config dataclass of ``command`` (``PaperConfig``, ``CompareConfig``, ...)."""
    if command == "paper":
        return paper.PaperConfig
    from factorq_trainers.runner import registry

    return registry.load(command).CONFIG


def reserved_fields(command: str = "paper") -> tuple[str, ...]:
    """The fields of ``command``'s config that the sweep sets itself."""
    return {"compare": COMPARE_RESERVED, "paper": RESERVED}.get(command, UNITS_RESERVED)


def nested_fields(command: str = "paper") -> list[str]:
    """The fields of ``command``'s config that are configs themselves: not sweepable."""
    hints = typing.get_type_hints(config_class(command))
    return [name for name, hint in hints.items() if dataclasses.is_dataclass(hint)]


def sweepable_fields(command: str = "paper") -> dict[str, Any]:
    """Field name -> type annotation of every field of ``command``'s config a sweep may set
    (``PaperConfig`` or ``CompareConfig``; nested configs and the sweep's own fields left out)."""
    kind = config_class(command)
    hints = typing.get_type_hints(kind)
    skipped = {*reserved_fields(command), *nested_fields(command)}
    return {f.name: hints[f.name] for f in fields(kind) if f.name not in skipped}


def config_digest(config: Any) -> str:
    """A short hash of the fields that decide ``config``'s numbers: a paper config's shard
    digest, or for a compare config every field but ``out``, ``threads`` and ``logger``; for a
    dependencies config every field but ``out``, ``threads`` and ``path`` (the compiled and the
    modular path give the same numbers bit for bit)."""
    if isinstance(config, paper.PaperConfig):
        return shards.digest(config)
    from factorq_trainers.experiments import compare

    if isinstance(config, compare.CompareConfig):
        values, ignored = compare.config_dict(config), ("out", "threads", "logger")
    else:  # a command of the runner: its DIGEST_IGNORED (fields that leave the numbers alone)
        module = sys.modules[type(config).__module__]
        values = _json(dataclasses.asdict(config))
        ignored = getattr(module, "DIGEST_IGNORED", ("out", "threads"))
    relevant = {key: value for key, value in values.items() if key not in ignored}
    return hashlib.sha256(json.dumps(relevant, sort_keys=True).encode()).hexdigest()[:16]


def _plain(value: Any) -> Any:
    """TOML lists as tuples (the configs' sequence fields), everything else as is."""
    return tuple(value) if isinstance(value, list) else value


@dataclass(frozen=True)
class SweepSpec:
    """A sweep: ``base`` values, ``grid`` axes (crossed with the ``configs`` list), ``seeds``
    per configuration in shards of ``shard_seeds``, results in ``out``."""

    base: tuple[tuple[str, Any], ...] = ()
    """Fields every configuration shares, as (name, value) pairs."""
    grid: tuple[tuple[str, tuple[Any, ...]], ...] = ()
    """Swept axes, as (name, values) pairs: configurations are their cartesian product."""
    configs: tuple[tuple[tuple[str, Any], ...], ...] = ((),)
    """Explicit configurations (each crossed with the grid)."""
    seeds: int = DEFAULT_SEEDS
    """Seeds (independent experiments per world and algorithm) of every configuration."""
    shard_seeds: int = DEFAULT_SHARD_SEEDS
    """Seeds per shard."""
    out: str = DEFAULT_OUT
    """Directory for sweep.json, sweep.md, the figures and shards/ (configs/ for compare)."""
    command: str = "paper"
    """Whose configs are swept: ``paper`` (sharded seeds), ``compare`` or ``dependencies``
    (whole configs)."""

    def __post_init__(self) -> None:
        check_command(self.command, "sweep")
        check_int("seeds", self.seeds, 1, INT32_MAX)
        check_int("shard_seeds", self.shard_seeds, 1, INT32_MAX)
        if not isinstance(self.out, str) or not self.out:
            raise SweepError(f"out={self.out!r} must be a directory path")
        if Path(self.out).exists() and not Path(self.out).is_dir():
            raise SweepError(f"out={self.out!r} is an existing file: give a directory")
        known = sweepable_fields(self.command)
        reserved, nested = reserved_fields(self.command), nested_fields(self.command)
        for where, names in (
            ("base", [name for name, _ in self.base]),
            ("grid", [name for name, _ in self.grid]),
            ("configs", [name for entry in self.configs for name, _ in entry]),
        ):
            for name in names:
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
        for name, values in self.grid:
            if not isinstance(values, tuple) or not values:
                raise SweepError(f"grid axis {name!r} needs a non-empty list of values")
            if len(set(map(repr, values))) != len(values):
                raise SweepError(f"grid axis {name!r} repeats a value: {list(values)}")
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
                raise SweepError(f"configurations {seen[key]} and {index} are the same")
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
        """The validated config of every point (a ``SweepError`` names the point and the value):
        ``PaperConfig``s, or ``CompareConfig``s for ``command="compare"``."""
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


def spec_from_mapping(data: dict[str, Any], source: str = "sweep file") -> SweepSpec:
    """A ``SweepSpec`` from a parsed TOML (or YAML) document."""
    if not isinstance(data, dict):
        raise SweepError(f"{source}: expected a table of keys, got {type(data).__name__}")
    unknown = sorted(set(data) - set(SPEC_KEYS))
    if unknown:
        raise SweepError(
            f"{source}: unknown key(s) {', '.join(unknown)}; known: {', '.join(SPEC_KEYS)}"
        )
    command = check_command(data.get("command", "paper"), source)
    if command != "paper" and "shard_seeds" in data:
        raise SweepError(
            f"{source}: shard_seeds does not apply to command={command!r}: its unit of work is a "
            "whole configuration (DQN's seeds share a random stream within their batch)"
        )
    for key in ("base", "grid"):
        if not isinstance(data.get(key, {}), dict):
            raise SweepError(f"{source}: [{key}] must be a table")
    configs = data.get("configs", [{}])
    if (
        not isinstance(configs, list)
        or not all(isinstance(c, dict) for c in configs)
        or not configs
    ):
        raise SweepError(f"{source}: configs must be a non-empty array of tables ([[configs]])")
    grid = []
    for name, values in data.get("grid", {}).items():
        if not isinstance(values, list):
            raise SweepError(f"{source}: grid axis {name!r} must be a list, got {values!r}")
        grid.append((name, tuple(_plain(value) for value in values)))
    extra = {key: data[key] for key in ("seeds", "shard_seeds", "out") if key in data}
    try:
        return SweepSpec(
            base=tuple((k, _plain(v)) for k, v in data.get("base", {}).items()),
            grid=tuple(grid),
            configs=tuple(tuple((k, _plain(v)) for k, v in entry.items()) for entry in configs),
            command=command,
            **extra,
        )
    except (ValueError, TypeError) as error:
        raise SweepError(f"{source}: {error}") from None


#: A sweep file is a few hundred bytes; far larger ones are not sweep files.
MAX_SPEC_BYTES = 1024 * 1024
#: Configurations one sweep may hold (each is a whole run): checked from the axes' lengths
#: before anything is expanded (10**9 points used to end in MemoryError, 10**5 in minutes of
#: silence).
MAX_CONFIGURATIONS = 10_000
#: TOML's strings, comments and brackets, for the nesting check before ``tomllib`` (which
#: recurses on nested arrays and inline tables).
_TOML_TOKENS = re.compile(
    r'"""[\s\S]*?"""'
    r"|'''[\s\S]*?'''"
    r'|"(?:[^"\\\n]|\\.)*"'
    r"|'[^'\n]*'"
    r"|#[^\n]*"
    r"|[\[\]{}]"
)


def _yaml_loader() -> type:
    """PyYAML's safe loader refusing aliases (a 433-byte alias bomb took a minute and gigabytes)
    and nesting past ``results.MAX_DEPTH`` (checked before the composer recurses)."""
    import yaml

    class Loader(yaml.SafeLoader):
        depth = 0

        def compose_node(self, parent, index):  # noqa: ANN001, ANN202 - PyYAML's signature
            if self.check_event(yaml.AliasEvent):
                mark = self.peek_event().start_mark
                raise yaml.YAMLError(
                    f"aliases (*name) are not allowed in a sweep file (line {mark.line + 1})"
                )
            if self.depth >= result_files.MAX_DEPTH:
                raise yaml.YAMLError(f"it nests deeper than {result_files.MAX_DEPTH} levels")
            self.depth += 1
            try:
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

    return Loader


def read_spec_file(path: str | Path) -> dict[str, Any]:
    """The document of a ``.toml`` sweep file (or ``.yaml``/``.yml`` where PyYAML is installed):
    bounded in size and nesting before it is parsed, YAML without aliases."""
    path = Path(path)
    try:
        if path.is_file() and path.stat().st_size > MAX_SPEC_BYTES:
            raise SweepError(f"sweep file {path} is larger than {MAX_SPEC_BYTES} bytes")
        text = path.read_text()
    except OSError as error:
        raise SweepError(f"cannot read sweep file {path}: {error.strerror}") from None
    except UnicodeDecodeError:
        raise SweepError(f"sweep file {path} is not UTF-8 text") from None
    if path.suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise SweepError(
                f"{path}: YAML needs PyYAML (pip install pyyaml); or use TOML"
            ) from None
        try:
            data = yaml.load(text, Loader=_yaml_loader()) or {}  # noqa: S506 - a safe loader
        except yaml.YAMLError as error:
            raise SweepError(f"{path}: not valid YAML ({' '.join(str(error).split())})") from None
    else:
        if result_files.nesting_depth(text, _TOML_TOKENS) > result_files.MAX_DEPTH:
            raise SweepError(f"{path} nests deeper than {result_files.MAX_DEPTH} levels")
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise SweepError(f"{path}: not valid TOML ({error})") from None
    if result_files.deeper_than(data, result_files.MAX_DEPTH):  # dotted keys nest too
        raise SweepError(f"{path} nests deeper than {result_files.MAX_DEPTH} levels")
    return data


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


# --------------------------------------------------------------------------------------------
# Running shards


def run_shards(
    pending: Sequence[paper.PaperConfig],
    directory: Path,
    executor: cluster.InProcess | cluster.DaskExecutor,
    done: Callable[[paper.PaperConfig], None],
) -> None:
    """Run ``pending`` shards on ``executor``, saving each one's file as soon as it arrives."""
    if isinstance(executor, cluster.DaskExecutor):
        function = functools.partial(shards.run_shard, threads=1)
    else:
        function = shards.run_shard
    names = [f"shard-{shards.digest(s)}-{s.first_seed}-{s.first_seed + s.seeds}" for s in pending]
    for index, metrics in executor.map(function, list(pending), names):
        shard = pending[index]
        shards.save(shards.shard_path(directory, shard), shard, metrics)
        done(shard)


def _missing(directory: Path, every: list[paper.PaperConfig]) -> list[paper.PaperConfig]:
    return [shard for shard in every if not shards.shard_path(directory, shard).is_file()]


def run_paper(
    config: paper.PaperConfig,
    executor: cluster.InProcess | cluster.DaskExecutor,
    shard_seeds: int = DEFAULT_PAPER_SHARD_SEEDS,
    progress: paper.ProgressCallback | None = None,
) -> dict[str, Any]:
    """``paper.run(config)``'s results, computed as shards of ``shard_seeds`` seeds on
    ``executor``, each kept in ``OUT/shards/`` (existing ones are not rerun). Identical numbers;
    ``timing`` says where and how they were computed."""
    started = time.perf_counter()
    directory = Path(config.out) / SHARDS_DIRECTORY
    every = shards.split(config, shard_seeds)
    pending = _missing(directory, every)
    per_seed = len(config.cells) * config.runs * config.episodes
    total_seeds = config.seeds
    state = {"seeds": total_seeds - sum(s.seeds for s in pending)}

    def report() -> None:
        if progress is not None:
            progress(
                paper.Progress(
                    state["seeds"] * per_seed,
                    total_seeds * per_seed,
                    state["seeds"] * len(config.cells),
                    total_seeds * len(config.cells),
                )
            )

    def done(shard: paper.PaperConfig) -> None:
        state["seeds"] += shard.seeds
        report()

    report()
    run_shards(pending, directory, executor, done)
    parts = [shards.load(shards.shard_path(directory, shard), shard) for shard in every]
    wall = time.perf_counter() - started
    env_steps = int(
        sum(part[key].sum() for part in parts for key in part if key.endswith("/steps"))
    )
    timing = {
        "wall_s": round(wall, 3),
        "backend": paper.resolve_backend(config),
        "threads": 1  # a worker's, or this process's as paper.run reports it
        if isinstance(executor, cluster.DaskExecutor)
        else config.threads or torch.get_num_threads(),
        "env_steps": env_steps,
        "env_steps_per_s": round(env_steps / max(wall, 1e-9)),
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "shards": {
            "where": executor.description,
            "seeds_per_shard": shard_seeds,
            "total": len(every),
            "run_now": len(pending),
        },
    }
    return shards.results(config, parts, timing)


def compare_result_path(directory: str | os.PathLike, config: Any) -> Path:
    """``directory/<digest>.json``: where a compare configuration's results are kept."""
    return Path(directory) / f"{config_digest(config)}.json"


def _compare_task(run_method: Callable[..., Any], item: tuple[Any, str]) -> Any:
    config, method = item
    return _compare_method(run_method, config, method)


def run_compare_configs(
    configs: Sequence[Any],
    directory: Path,
    executor: cluster.InProcess | cluster.DaskExecutor,
    done: Callable[[], None],
) -> None:
    """Run every method of every compare config in ``configs`` as one task each on
    ``executor``; when a config's methods are all in, write its ``compare.summarise`` dict
    (what ``compare.run`` returns, ``timing`` aside) to ``compare_result_path``, atomically.
    ``done()`` is called per method finished."""
    from factorq_trainers.experiments import compare

    items = [(config, method) for config in configs for method in config.methods]
    owner = [index for index, config in enumerate(configs) for _ in config.methods]
    names = [f"compare-{config_digest(config)}-{method}" for config, method in items]
    runs: list[dict[str, Any]] = [{} for _ in configs]
    function = functools.partial(_compare_task, compare.run_method)
    for task, result in executor.map(function, items, names):
        index = owner[task]
        config = configs[index]
        runs[index][items[task][1]] = result
        done()
        if len(runs[index]) == len(config.methods):
            results = compare.summarise(config, {m: runs[index][m] for m in config.methods})
            results["timing"] = {
                "method_wall_s": round(sum(float(r["wall_s"]) for r in runs[index].values()), 3),
                "where": executor.description,
            }
            text = result_files.dumps(results)
            directory.mkdir(parents=True, exist_ok=True)
            result_files.write_atomic(
                compare_result_path(directory, config), lambda path, t=text: path.write_text(t)
            )
            runs[index] = {}


def compare_cells(results: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per method and world of a ``comparison.json`` dict: its measures as means with 95%
    intervals across seeds (``steps_to_threshold`` only where every seed reached it)."""
    cells = {}
    for method, worlds in results["results"].items():
        for world, entry in worlds.items():
            reached = entry["steps_to_threshold_per_seed"]
            steps = {"mean": entry["steps_to_threshold"], "ci95": None}
            if entry["steps_to_threshold"] is not None:
                seed = results["config"].get("seed", 0)  # compare's bootstrap, its seed
                bounded = functools.partial(stats.bootstrap_mean_ci, seed=seed)
                steps["ci95"] = result_files.interval_or_none(stats.scalar_ci(reached, bounded)[1:])
            cells[f"{world}/{method}"] = {
                "world": world,
                "algorithm": method,
                "steps_to_threshold": steps,
                **{
                    measure: {
                        "mean": entry[measure],
                        "ci95": result_files.interval_or_none(entry[f"{measure}_ci95"]),
                    }
                    for measure in (
                        "collisions",
                        "greedy_collisions",
                        "avoidable_greedy_collisions",
                    )
                },
                "seeds_reached": entry["seeds_reached"],
                "per_seed": {"steps_to_threshold": reached},
            }
    return cells


def run_compare_sweep(
    spec: SweepSpec,
    executor: cluster.InProcess | cluster.DaskExecutor,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """``run_sweep`` of a compare spec: every configuration not already in ``OUT/configs/``
    run whole (one task per method), then gathered into ``sweep.json``'s dict."""
    from factorq_trainers.experiments import compare

    started = time.perf_counter()
    directory = Path(spec.out) / CONFIGS_DIRECTORY
    configs = spec.configurations()
    pending = [c for c in configs if not compare_result_path(directory, c).is_file()]
    total = sum(len(config.methods) for config in configs)
    count = {"done": total - sum(len(config.methods) for config in pending)}
    if progress is not None:
        progress(count["done"], total)

    def done() -> None:
        count["done"] += 1
        if progress is not None:
            progress(count["done"], total)

    run_compare_configs(pending, directory, executor, done)
    return _gathered(
        spec,
        "compare",
        COMPARE_MEASURES,
        pending,
        started,
        executor,
        compare.config_dict,
        compare_cells,
    )


def _gathered(
    spec: SweepSpec,
    command: str,
    measures: Sequence[str],
    pending: list,
    started: float,
    executor: cluster.InProcess | cluster.DaskExecutor,
    config_dict: Callable[[Any], dict[str, Any]],
    cells: Callable[[dict[str, Any]], dict[str, dict[str, Any]]],
) -> dict[str, Any]:
    """``sweep.json``'s dict of a sweep whose configurations each ran whole (``compare``,
    ``dependencies``): one row per configuration read back from ``OUT/configs/``, its cells
    taken by ``cells``; ``pending``: the configurations run by this call."""
    computed = time.perf_counter() - started
    directory = Path(spec.out) / CONFIGS_DIRECTORY
    configs = spec.configurations()
    rows = []
    for config, point in zip(configs, spec.points(), strict=True):
        path = compare_result_path(directory, config)
        try:  # a kept file is the user's: it may have been edited or cut short
            kept = cells(json.loads(path.read_text()))
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as error:
            raise ValueError(
                f"configuration file {path} is not a factorq {command} result ({error!r}): "
                f"delete it to rerun that configuration"
            ) from None
        rows.append(
            {
                "values": point,
                "digest": config_digest(config),
                "config": config_dict(config),
                "results_file": f"{CONFIGS_DIRECTORY}/{path.name}",
                "cells": kept,
                "claims": {},
            }
        )
    return {
        "command": command,
        "measures": list(measures),
        "axes": spec.axes,
        "base": {name: _json(value) for name, value in spec.base},
        "seeds": spec.seeds,
        "shard_seeds": None,
        "configurations": [_json(row) for row in rows],
        "timing": {
            "wall_s": round(time.perf_counter() - started, 3),
            "compute_s": round(computed, 3),
            "where": executor.description,
            "configurations_total": len(configs),
            "configurations_run_now": len(pending),
        },
        "software": paper.software_versions(),
    }


def _units_task(command: str, config: Any) -> dict[str, Any]:
    from factorq_trainers.runner import frame, registry

    return frame.run_in_process(registry.load(command), config)


def run_units_sweep(
    spec: SweepSpec,
    executor: cluster.InProcess | cluster.DaskExecutor,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """``run_sweep`` of a spec of a command of the runner (``dependencies``, ``minigrid``, ...):
    every configuration not already in ``OUT/configs/`` run whole
    (``frame.run_in_process``, one task each) and kept there as its results dict, then gathered
    into ``sweep.json``'s dict with the cells of the command's ``sweep_cells``."""
    started = time.perf_counter()
    directory = Path(spec.out) / CONFIGS_DIRECTORY
    configs = spec.configurations()
    pending = [c for c in configs if not compare_result_path(directory, c).is_file()]
    done = len(configs) - len(pending)
    if progress is not None:
        progress(done, len(configs))
    names = [f"{spec.command}-{config_digest(config)}" for config in pending]
    task = functools.partial(_units_task, spec.command)
    for index, results in executor.map(task, pending, names):
        text = result_files.dumps(results)
        directory.mkdir(parents=True, exist_ok=True)
        result_files.write_atomic(
            compare_result_path(directory, pending[index]), lambda path, t=text: path.write_text(t)
        )
        done += 1
        if progress is not None:
            progress(done, len(configs))
    reports = _reports_of(spec.command)
    return _gathered(
        spec,
        spec.command,
        reports.SWEEP_MEASURES,
        pending,
        started,
        executor,
        lambda config: _json(dataclasses.asdict(config)),
        reports.sweep_cells,
    )


def run_sweep(
    spec: SweepSpec,
    executor: cluster.InProcess | cluster.DaskExecutor,
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Run every shard of ``spec`` not already on disk, then gather ``sweep.json``'s dict.

    ``progress(done, total)`` counts shards (those found on disk are done from the start); for
    a compare spec, ``run_compare_sweep``, counting methods.
    """
    if spec.command == "compare":
        return run_compare_sweep(spec, executor, progress)
    if spec.command != "paper":
        return run_units_sweep(spec, executor, progress)
    started = time.perf_counter()
    directory = Path(spec.out) / SHARDS_DIRECTORY
    configs = spec.configurations()
    every = [shard for config in configs for shard in shards.split(config, spec.shard_seeds)]
    pending = _missing(directory, every)
    count = {"done": len(every) - len(pending)}
    if progress is not None:
        progress(count["done"], len(every))

    def done(_: paper.PaperConfig) -> None:
        count["done"] += 1
        if progress is not None:
            progress(count["done"], len(every))

    run_shards(pending, directory, executor, done)
    computed = time.perf_counter() - started
    rows = []
    for config, point in zip(configs, spec.points(), strict=True):
        parts = [
            shards.load(shards.shard_path(directory, shard), shard)
            for shard in shards.split(config, spec.shard_seeds)
        ]
        summary = paper.summarise(config, shards.concatenate(config, parts))
        rows.append(
            {
                "values": point,
                "digest": shards.digest(config),
                "config": paper.config_dict(config),
                "cells": {
                    name: {
                        "world": cell["world"],
                        "algorithm": cell["algorithm"],
                        **cell["summary"],
                        "per_seed": cell["per_seed"],
                    }
                    for name, cell in summary["cells"].items()
                },
                "claims": {
                    name: {key: claim[key] for key in ("value", "ci95", "pass")}
                    for name, claim in summary["claims"].items()
                },
            }
        )
    return {
        "command": "paper",
        "measures": list(MEASURES),
        "axes": spec.axes,
        "base": {name: _json(value) for name, value in spec.base},
        "seeds": spec.seeds,
        "shard_seeds": spec.shard_seeds,
        "configurations": [_json(row) for row in rows],
        "timing": {
            "wall_s": round(time.perf_counter() - started, 3),
            "compute_s": round(computed, 3),
            "where": executor.description,
            "shards_total": len(every),
            "shards_run_now": len(pending),
        },
        "software": paper.software_versions(),
    }


def _json(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _json(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_json(item) for item in value]
    return value


# --------------------------------------------------------------------------------------------
# Command line


def add_paper_options(parser: argparse.ArgumentParser) -> None:
    """The cluster options of ``factorq paper``: ``cluster.add_options`` and ``--shard-seeds``."""
    cluster.add_options(parser)
    parser.add_argument(
        "--shard-seeds",
        type=int,
        metavar="K",
        help="With --cluster or --scheduler: seeds per shard (the unit of work; finished shards "
        "are kept in OUT/shards/ and not rerun, so a killed run resumes). Same numbers as one "
        f"process. (default: {DEFAULT_PAPER_SHARD_SEEDS})",
        default=argparse.SUPPRESS,
    )


def paper_executor(args: argparse.Namespace) -> cluster.InProcess | cluster.DaskExecutor | None:
    """The executor ``factorq paper``'s options ask for: ``None`` for the usual in-process run,
    else an open one (a ``ValueError`` in one line when it cannot be had)."""
    names = ("cluster", "scheduler", "connect_timeout", "shard_seeds")
    if not any(hasattr(args, name) for name in names):
        return None
    for name in ("checkpoint_every", "resume"):
        if hasattr(args, name):
            option = "--" + name.replace("_", "-")
            raise SweepError(
                f"{option} does not apply to a sharded run: its finished shards, kept in "
                f"OUT/{SHARDS_DIRECTORY}/, are what a rerun resumes from (leave {option} out)"
            )
    check_int(
        "--shard-seeds", getattr(args, "shard_seeds", DEFAULT_PAPER_SHARD_SEEDS), 1, INT32_MAX
    )
    return cluster.executor_from_args(args) or cluster.InProcess()


def run_paper_on(
    executor: cluster.InProcess | cluster.DaskExecutor,
    config: paper.PaperConfig,
    args: argparse.Namespace,
    progress: paper.ProgressCallback | None = None,
) -> dict[str, Any]:
    """``run_paper`` with ``args.shard_seeds``, closing ``executor`` afterwards."""
    try:
        shard_seeds = getattr(args, "shard_seeds", DEFAULT_PAPER_SHARD_SEEDS)
        return run_paper(config, executor, shard_seeds, progress)
    finally:
        executor.close()


def _compare_method(run_method: Callable[..., Any], config: Any, method: str) -> Any:
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)
    try:
        return run_method(config, method)
    finally:
        torch.set_num_threads(threads)


def run_compare_on(
    executor: cluster.InProcess | cluster.DaskExecutor,
    config: Any,
    run_method: Callable[..., dict[str, Any]],
    summarise: Callable[[Any, dict[str, Any]], dict[str, Any]],
) -> dict[str, Any]:
    """``factorq compare`` with one task per method on ``executor`` (closed afterwards): a
    method's batch is the unit, so every method, DQN included, repeats its in-process numbers.
    ``run_method`` and ``summarise`` are ``factorq_trainers.experiments.compare``'s (passed in: this
    module does not import it). Seeds are not sharded: DQN's seeds share a random stream within
    their batch."""
    started = time.perf_counter()
    methods = list(config.methods)
    bar = _ShardBar("factorq compare", "method")
    try:
        bar(0, len(methods))
        function = functools.partial(_compare_method, run_method, config)
        runs: dict[str, Any] = {}
        for index, result in executor.map(function, methods, [f"compare-{m}" for m in methods]):
            runs[methods[index]] = result
            bar(len(runs), len(methods))
        bar.close()
        where = executor.description
    finally:
        executor.close()
    results = summarise(config, {method: runs[method] for method in methods})
    results["timing"] = {"wall_s": round(time.perf_counter() - started, 3), "where": where}
    return results


def build_parser(prog: str = "factorq sweep") -> argparse.ArgumentParser:
    parser = Parser(
        prog=prog,
        description="Run a grid of `factorq paper` configurations, each with --seeds seeds, as "
        "shards of --shard-seeds seeds (or, with --command compare, of `factorq compare` "
        "configurations, each run whole); write sweep.json, sweep.md and a figure per axis to "
        "--out. Finished shards (configurations) are kept in OUT/shards/ (OUT/configs/) and not "
        "rerun (a killed sweep resumes).",
    )
    parser.add_argument("spec", nargs="?", metavar="SPEC", help="a .toml (or .yaml) sweep file")
    parser.add_argument(
        "--command",
        metavar="NAME",
        default=argparse.SUPPRESS,
        help="Whose configs to sweep: paper (seeds sharded), compare (each configuration "
        "run whole, one task per method) or any other command (dependencies, minigrid, ...: "
        "each configuration one task). "
        "(default: the file's command, else paper)",
    )
    parser.add_argument(
        "--grid",
        action="append",
        metavar="FIELD=V1,V2",
        default=[],
        help="A swept axis: a field of the --command's config and its values (repeatable; "
        "crossed).",
    )
    parser.add_argument(
        "--set",
        action="append",
        metavar="FIELD=VALUE",
        default=[],
        help="A base value shared by every configuration (repeatable).",
    )
    parser.add_argument("--seeds", type=int, metavar="N", default=argparse.SUPPRESS,
                        help=f"Seeds per configuration. (default: {DEFAULT_SEEDS})")  # fmt: skip
    parser.add_argument("--shard-seeds", type=int, metavar="K", default=argparse.SUPPRESS,
                        help=f"Seeds per shard. (default: {DEFAULT_SHARD_SEEDS})")  # fmt: skip
    parser.add_argument("--out", metavar="DIR", default=argparse.SUPPRESS,
                        help=f"Output directory. (default: {DEFAULT_OUT})")  # fmt: skip
    parser.add_argument(
        "--force",
        action="store_true",
        help="Replace the sweep.json and sweep.md of an earlier sweep in --out (its finished "
        "shards are reused either way). Without it, an --out holding them is refused.",
    )
    cluster.add_options(parser)
    return parser


def _pairs(options: list[str], option: str) -> list[tuple[str, str]]:
    pairs = []
    for text in options:
        name, equals, value = text.partition("=")
        if not equals or not name:
            raise SweepError(f"{option} {text!r} is not FIELD=VALUE")
        pairs.append((name.strip().replace("-", "_"), value.strip()))
    return pairs


def spec_from_args(args: argparse.Namespace) -> SweepSpec:
    """The sweep of the file (if any) with the options applied over it."""
    data = read_spec_file(args.spec) if args.spec else {}
    source = args.spec or "options"
    if not isinstance(data, dict):
        raise SweepError(f"{source}: expected a table of keys, got {type(data).__name__}")
    data = dict(data)
    if hasattr(args, "command"):
        data["command"] = args.command
    command = check_command(data.get("command", "paper"), source)
    base = dict(data.get("base", {}) if isinstance(data.get("base", {}), dict) else {})
    for name, text in _pairs(args.set, "--set"):
        base[name] = parse_value(name, text, command)
    grid = dict(data.get("grid", {}) if isinstance(data.get("grid", {}), dict) else {})
    for name, text in _pairs(args.grid, "--grid"):
        annotation = sweepable_fields(command).get(name)
        if typing.get_origin(annotation) is tuple:  # one name per value: worlds=static,dynamic
            grid[name] = [[item] for item in text.split(",") if item]
        else:
            grid[name] = [parse_value(name, item, command) for item in text.split(",") if item]
    if base:
        data["base"] = base
    if grid:
        data["grid"] = grid
    for key in ("seeds", "shard_seeds", "out"):
        if hasattr(args, key):
            data[key] = getattr(args, key)
    if not data.get("grid") and data.get("configs", [{}]) == [{}]:
        raise SweepError("nothing to sweep: give a sweep file, or --grid FIELD=V1,V2")
    return spec_from_mapping(data, source)


class _ShardBar:
    """A tqdm bar of shards (or other tasks) done, with the time left."""

    def __init__(self, description: str = "factorq sweep", unit: str = "shard") -> None:
        self.bar = None
        self.description = description
        self.unit = unit

    def __call__(self, done: int, total: int) -> None:
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(
                total=total,
                initial=done,
                desc=self.description,
                unit=self.unit,
                dynamic_ncols=True,
                mininterval=0.5 if sys.stderr.isatty() else 30.0,
                file=sys.stderr,
            )
        self.bar.update(done - self.bar.n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def main(argv: list[str] | None = None) -> int:
    """``factorq sweep ...``; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    except SystemExit as exit_:
        return exit_.code if isinstance(exit_.code, int) else EXIT_USAGE
    try:
        spec = spec_from_args(args)
        where = cluster.where_from_args(args)
        workers = 1 if where.local_workers is None else where.local_workers or os.cpu_count() or 1
        if spec.command not in SPECIAL:  # a command of the runner: its own estimate, if any
            from factorq_trainers.runner import registry

            module = registry.load(spec.command)
            estimate = max(
                (
                    module.estimate(config)
                    if hasattr(module, "estimate")
                    else resources.Estimate({}, 0, exact_steps=False)
                    for config in spec.configurations()
                ),
                key=lambda estimate: estimate.bytes,
            )  # per configuration: a worker runs one at a time
            hint = getattr(module, "HINT", "use fewer --seeds or smaller configurations")
        elif spec.command == "compare":
            estimate = max(
                (resources.compare_estimate(config) for config in spec.configurations()),
                key=lambda estimate: estimate.bytes,
            )  # per comparison: a worker runs one method of it at a time
            hint = "use fewer --seeds, or smaller steps or size"
        else:
            estimate = resources.sweep_estimate(spec.configurations(), spec.shard_seeds, workers)
            hint = resources.SWEEP_HINT
        large = resources.check(estimate, "sweep", hint)
        if large is not None:
            print(large, file=sys.stderr)
        executor = cluster.open_executor(where)  # before anything is written
    except (ValueError, TypeError) as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    try:  # the only writer of --out from here on, checked before any work
        with outdir.claim(
            spec.out, outputs=(sweep_report.JSON_FILE, sweep_report.REPORT_FILE), force=args.force
        ):
            return _run_sweep_command(parser, spec, executor)
    except outdir.OutputDirError as error:
        executor.close()
        print(f"{parser.prog}: error: {str(error).replace('out=', '--out=')}", file=sys.stderr)
        return EXIT_USAGE


def _run_sweep_command(parser, spec: SweepSpec, executor) -> int:
    configs = spec.configurations()
    if spec.command == "compare":
        tasks = sum(len(config.methods) for config in configs)
        work = f"{tasks} method tasks (factorq compare)"
    elif spec.command == "paper":
        work = f"{len(configs) * math.ceil(spec.seeds / spec.shard_seeds)} shards"
    else:
        work = f"{len(configs)} configuration tasks (factorq {spec.command})"
    print(
        f"{len(configs)} configurations x {spec.seeds} seeds = {work}, {executor.description}",
        file=sys.stderr,
    )
    unit = {"compare": "method", "paper": "shard"}.get(spec.command, "configuration")
    bar = _ShardBar(unit=unit)
    try:
        sweep = run_sweep(spec, executor, bar)
        bar.close()
        paths = sweep_report.write_outputs(sweep, spec.out)
    except KeyboardInterrupt:
        bar.close()
        print(f"{parser.prog}: interrupted (run it again to resume)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (OSError, ValueError) as error:  # a full disk; a kept shard or result file gone bad
        bar.close()
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        executor.close()
    print(f"sweep in {Path(spec.out)}/ after {sweep['timing']['wall_s']:.1f} s:")
    for path in paths.values():
        print(f"  {path}")
    return 0
