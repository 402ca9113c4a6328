"""The frame every command declared by units runs in: ``execute`` parses, validates, estimates
the memory, claims ``--out``, resumes, runs the pending units under one progress bar (in-process
or on Dask), summarises and writes the files, once for every command. The protocol a command
module declares (``CONFIG``, ``units``, ``run_unit``, ``summarise`` and the optional hooks) and
the order of the steps are written out in docs/architecture.md ("Adding a command",
``runner/frame.py``); ``finish(config, outcomes, out)`` runs once the three files are written and
before the kept units go (a kill during it resumes to it again).

**Resume** is per unit (``kept.UnitStore``, ``OUT/units/``): ``--resume OUT`` reruns only the units
without a kept file, with the saved config. A unit's result goes through JSON whether it was
computed now or read back, so a resumed run writes the same files as an uninterrupted one.

**The envelope** of every results file: ``schema_version``, ``command``, ``config``,
``software``, ``timing`` (``wall_s``, ``where``, ``units``, ``units_resumed``) and the command's
own entries (``summarise``'s dict) beside them.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import importlib
import importlib.util
import json
import re
import sys
import time
import typing
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

from factorq_trainers.runner import cluster, options, outdir, registry, resources, results
from factorq_trainers.runner import kept as kept_files

EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for Ctrl-C
FORCE_HELP = (
    "Replace the results of an earlier run in --out (they are kept until the new ones are "
    "written, all at once). Without it, an --out holding results is refused before any work."
)
RESUME_HELP = (
    "Continue the interrupted run whose --out is DIR: the units it finished (kept in DIR/units/) "
    "are not rerun, with the config saved there (options repeated must match; --threads may "
    "change) and the same numbers as an uninterrupted run."
)
#: The envelope's own entries: ``summarise`` may not return them.
ENVELOPE = ("schema_version", "command", "config", "software")


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: ``factorq paper: error: ...`` (exit 2)."""

    def error(self, message: str) -> typing.NoReturn:
        error(self, message)
        raise SystemExit(EXIT_USAGE)


def error(parser: argparse.ArgumentParser, message: str) -> None:
    """Print ``PROG: error: MESSAGE (see PROG --help)`` on stderr."""
    print(f"{parser.prog}: error: {message} (see {parser.prog} --help)", file=sys.stderr)


def failure(parser: argparse.ArgumentParser, message: Any) -> None:
    """Print ``PROG: error: MESSAGE`` (a failure that is not the user's input)."""
    print(f"{parser.prog}: error: {message}", file=sys.stderr)


def as_option(message: str, config: type, extra: tuple[str, ...] = ()) -> str:
    """``seeds=0 is out of range`` -> ``--seeds=0 is out of range`` (the names the user typed):
    a leading ``name:`` and every ``name=`` of a field of ``config`` or of ``extra``."""
    names = {field.name for field in dataclasses.fields(config)} | set(extra)

    def spelled(match: re.Match) -> str:
        return options.option_name(match[1]) if match[1] in names else match[1]

    message = re.sub(r"^(\w+)(?=:)", spelled, message, count=1)
    return re.sub(r"(?<![\w.'-])(\w+)(?==)", spelled, message)


# --------------------------------------------------------------------------------------------
# The declaration's optional parts, with their defaults


def files(module: ModuleType) -> dict[str, str]:
    """``{"json", "report", "figure"}`` -> file names: ``FILES``, else ``NAME.json/.md/.png``."""
    return {**registry.default_files(module.NAME), **getattr(module, "FILES", {})}


def work(module: ModuleType, config: Any, unit: dict[str, Any]) -> int:
    """The unit's share of the progress bar (``work``, else 1)."""
    return int(module.work(config, unit)) if hasattr(module, "work") else 1


def plain(value: Any) -> Any:
    """A config (or anything made of dataclasses, tuples, dicts) as JSON values."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        value = dataclasses.asdict(value)
    return json.loads(json.dumps(value))


def config_from_dict(config_type: type, data: dict[str, Any]) -> Any:
    """``config_type(**data)`` with JSON lists back as the tuples the dataclass holds, and a
    JSON object back as the nested config of a field whose default is one (``compare``'s
    ``dqn``, ...)."""
    nested = {
        field.name: type(field.default)
        for field in dataclasses.fields(config_type)
        if dataclasses.is_dataclass(field.default)
    }
    values = {}
    for key, value in data.items():
        if isinstance(value, list):
            value = tuple(value)
        elif isinstance(value, dict) and key in nested:
            value = config_from_dict(nested[key], value)
        values[key] = value
    return config_type(**values)


def prepared(module: ModuleType, config: Any) -> tuple[list[dict[str, Any]], str | None]:
    """``module.prepare(config)``, the memory estimate checked before any allocation, and then
    the ``checked_units``; with the line to print for a large run (``resources.check``)."""
    if hasattr(module, "prepare"):
        module.prepare(config)
    large = None
    if hasattr(module, "estimate"):
        large = resources.check(module.estimate(config), "experiment", getattr(module, "HINT", ""))
    return checked_units(module, config), large


def checked_units(module: ModuleType, config: Any) -> list[dict[str, Any]]:
    """``module.units(config)``, each with a unique string ``id`` (a RuntimeError otherwise: the
    declaration's bug, not the user's, as is a command without a ``UNIT_RESULT`` schema)."""
    if not hasattr(module, "UNIT_RESULT"):
        raise RuntimeError(f"{module.NAME} declares no UNIT_RESULT (its units' schema, kept.py)")
    units = module.units(config)
    ids = [unit.get("id") if isinstance(unit, dict) else None for unit in units]
    if any(not isinstance(unit_id, str) or not unit_id for unit_id in ids):
        raise RuntimeError(f"{module.NAME}.units: every unit needs a non-empty string 'id'")
    if len(set(ids)) != len(ids):
        raise RuntimeError(f"{module.NAME}.units: unit ids repeat")
    return units


def through_json(value: Any) -> Any:
    """``value`` as a results file would give it back (non-finite numbers as None)."""
    return json.loads(results.dumps(value))


def unit_result(module: ModuleType, config: Any, unit: dict[str, Any], result: Any) -> Any:
    """``result`` of ``unit`` computed now, through JSON and checked against the command's
    ``UNIT_RESULT`` (what a kept one must pass too): a RuntimeError, the declaration's bug,
    when it does not fit."""
    result = through_json(result)
    problem = kept_files.schema_problem(result, module.UNIT_RESULT)
    if problem is None and hasattr(module, "check_unit"):
        problem = module.check_unit(config, unit, result)
    if problem is not None:
        raise RuntimeError(
            f"{module.NAME}.run_unit({unit['id']!r}) does not fit UNIT_RESULT: {problem}"
        )
    return result


def envelope(
    module: ModuleType,
    config: Any,
    summary: dict[str, Any],
    *,
    wall_s: float,
    where: str = "in-process",
    units: int = 0,
    resumed: int = 0,
) -> dict[str, Any]:
    """The results file's dict: the envelope around ``summary`` (``summarise``'s)."""
    clash = [key for key in ENVELOPE if key in summary]
    if clash:
        raise RuntimeError(f"{module.NAME}.summarise returned the envelope's {clash}")
    timing = {"wall_s": wall_s, "where": where, "units": units, "units_resumed": resumed}
    rest = {key: value for key, value in summary.items() if key != "timing"}
    return {
        "schema_version": results.SCHEMA_VERSION,
        "command": module.NAME,
        "config": plain(config),
        "software": results.software_versions(),
        "timing": {**timing, **summary.get("timing", {})},
        **rest,
    }


def run_in_process(
    module: ModuleType,
    config: Any,
    progress: Callable[[int], None] | None = None,
    run_unit: Callable[[dict[str, Any], Any], Any] | None = None,
) -> dict[str, Any]:
    """Every unit here, in order, summarised into the envelope; no files (the protocol's
    ``run(config)``, for tests and notebooks). ``run_unit(unit, progress)``: what runs a unit
    instead of ``module.run_unit(config, unit, progress)`` (``paper.run``'s other world)."""
    started = time.perf_counter()
    units, _ = prepared(module, config)
    run_unit = run_unit or functools.partial(module.run_unit, config)
    outcomes = [unit_result(module, config, unit, run_unit(unit, progress)) for unit in units]
    summary = module.summarise(config, outcomes)
    return envelope(module, config, summary, wall_s=time.perf_counter() - started, units=len(units))


def progress_bar(**options: Any) -> Any:
    """A tqdm bar on stderr (``options``: tqdm's), redrawn at most every 0.5 s on a terminal and
    every 30 s into a log file."""
    from tqdm.auto import tqdm

    interval = 0.5 if sys.stderr.isatty() else 30.0
    return tqdm(file=sys.stderr, dynamic_ncols=True, mininterval=interval, **options)


def run_unit_task(module_name: str, config: Any, unit: dict[str, Any]) -> Any:
    """One unit on a worker (picklable: the module travels by name)."""
    module = importlib.import_module(module_name)
    return unit_result(module, config, unit, module.run_unit(config, unit, None))


# --------------------------------------------------------------------------------------------
# The command line


def add_frame_options(parser: argparse.ArgumentParser) -> None:
    """``--force``, ``--resume DIR`` and the cluster options (``--cluster``, ``--scheduler``,
    ``--connect-timeout``)."""
    parser.add_argument("--force", action="store_true", default=argparse.SUPPRESS, help=FORCE_HELP)
    parser.add_argument("--resume", metavar="DIR", default=argparse.SUPPRESS, help=RESUME_HELP)
    cluster.add_options(parser)


#: Config fields a resumed run may change: they do not change the numbers.
RESUMABLE_CHANGES = ("out", "threads")


def resumed_config(
    saved: dict[str, Any], given: dict[str, Any], directory: str, config_type: type
) -> Any:
    """The config to resume the run kept in ``directory`` with: the ``saved`` config dict, with
    the ``given`` options (field -> value) that may change (``RESUMABLE_CHANGES``).

    Any other given option must equal the saved value (a ValueError names each that differs);
    ``out`` must be ``directory`` (the saved spelling is kept when it names the same directory,
    so the results repeat it).
    """
    out = saved.get("out", "")
    if not out or Path(out).resolve() != Path(directory).resolve():
        out = str(directory)
    if "out" in given and Path(given["out"]).resolve() != Path(directory).resolve():
        raise ValueError(
            f"out='{given['out']}' differs from the resumed directory '{directory}': a resumed "
            f"run writes where its units are kept (leave --out out)"
        )
    try:
        kept_config = config_from_dict(config_type, {**saved, "out": out})
    except (ValueError, TypeError) as problem:
        raise ValueError(
            f"resume='{directory}': the kept run's config is unusable here ({problem})"
        ) from None
    merged = config_from_dict(config_type, {**plain(kept_config), **given, "out": out})
    differing = [
        f"{name}={kept_files.short(value, 40)} given, {kept_files.short(saved.get(name), 40)} kept"
        for name, value in plain(merged).items()
        if name not in RESUMABLE_CHANGES and saved.get(name) != value
    ]
    if differing:
        raise ValueError(
            f"resume='{directory}' holds a run of a different config: {'; '.join(differing)} "
            f"(leave these options out to resume it, or start a new run with another --out)"
        )
    return merged


def write_outputs(
    module: ModuleType, results_dict: dict[str, Any], out: Path, figure_process: Any = None
) -> dict[str, Path]:
    """The results file, the Markdown and the figure (those the command declares), at once;
    ``figure_process`` (``reports.figure_process``, a command declaring ``FIGURE_PROCESS``)
    draws the figure meanwhile."""
    names = files(module)
    report = report_module(module)
    draw = functools.partial(report.figure, results_dict) if hasattr(report, "figure") else None
    if draw is not None and figure_process is not None:
        out.mkdir(parents=True, exist_ok=True)
        report.send_figure(figure_process, results_dict, out)  # drawn while the rest is written
        draw = functools.partial(draw, figure_process=figure_process)
    json_file = (out / names["json"], lambda p: p.write_text(results.dumps(results_dict)))
    return write_report(report, results_dict, out, names, draw, {"json": json_file})


def write_report(
    report: ModuleType,
    data: dict[str, Any],
    out: Path,
    names: dict[str, str],
    draw: Callable[[Path], Any] | None,
    writers: dict[str, tuple[Path, Callable[[Path], Any]]] | None = None,
) -> dict[str, Path]:
    """``report``'s Markdown of ``data`` (where it has ``markdown``) and the figure ``draw``
    draws, with the other ``writers`` (name -> (path, writer)), written at once; ``names``: the
    command's file names. Returns the paths by name. A figure that fails to draw (matplotlib's
    error, from deep inside) is one ``FigureError`` line naming it, and no file is written."""
    writers = dict(writers or {})
    if hasattr(report, "markdown"):
        writers["report"] = (out / names["report"], lambda p: p.write_text(report.markdown(data)))
    if draw is not None:
        figure = functools.partial(_drawn, draw, names["figure"])
        writers["figure"] = (out / names["figure"], figure)
    results.write_all_atomic(dict(writers.values()))
    return {name: path for name, (path, _) in writers.items()}


def _drawn(draw: Callable[[Path], Any], name: str, path: Path) -> None:
    try:
        draw(path)
    except Exception as error:  # matplotlib's, from deep inside: one line
        raise results.FigureError(
            f"drawing {name} failed: {type(error).__name__}: {error}"
        ) from error


def report_module(module: ModuleType) -> ModuleType:
    """Where ``module``'s ``markdown`` and ``figure`` live: the ``report.py`` beside it (a
    command's folder, ``trainers/commands/<name>/``), else ``module`` itself."""
    package = module.__name__.rpartition(".")[0]
    if package and importlib.util.find_spec(f"{package}.report") is not None:
        return importlib.import_module(f"{package}.report")
    return module


def execute(
    module: ModuleType,
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    figure_process: Any = None,
) -> int:
    """Run the command ``module`` declares with the parsed ``args``; the exit status.
    ``figure_process``: the helper that draws the figure (``cli`` starts it for a command that
    declares ``FIGURE_PROCESS``)."""
    store = kept_files.UnitStore(args.resume) if hasattr(args, "resume") else None
    told: list[str] = []  # notices, printed once the run is accepted: a refusal stays one line
    try:
        given = options.given_options(args, module.CONFIG)
        if store is None:
            config = module.CONFIG(**given)
        else:
            saved = store.saved_run(module.NAME)["config"]
            config = resumed_config(saved, given, args.resume, module.CONFIG)
        units, large = prepared(module, config)
        told.append(large or "")
        where = cluster.where_from_args(args)  # --cluster off: in-process, whatever the default
        executor = None if where.in_process else cluster.open_executor(where)
        chosen = any(hasattr(args, name) for name in ("cluster", "scheduler"))
        if executor is None and not chosen and hasattr(module, "processes"):
            executor = _default_processes(parser, module, config, units, told)
    except (ValueError, TypeError, ModuleNotFoundError) as problem:
        error(parser, as_option(str(problem), module.CONFIG, ("resume",)))
        return EXIT_USAGE
    told += [getattr(module, "NOTICE", None) or ""]
    force, outputs = hasattr(args, "force"), tuple(files(module).values())
    try:
        with outdir.claim(config.out, outputs=outputs, force=force, resume=store is not None):
            return _run(module, config, units, store, executor, force, figure_process, told)
    except (outdir.OutputDirError, ValueError) as problem:
        error(parser, as_option(str(problem), module.CONFIG, ("resume",)))
        return EXIT_USAGE
    except KeyboardInterrupt:
        kept = kept_files.UnitStore(config.out).exists()
        resume = f" (resume it with --resume {config.out})" if kept else ""
        print(f"{parser.prog}: interrupted{resume}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (OSError, results.FigureError) as problem:  # a full disk, a figure not drawn: one line
        failure(parser, problem)
        return EXIT_FAILURE
    finally:
        if executor is not None:
            executor.close()


def _default_processes(
    parser: argparse.ArgumentParser,
    module: ModuleType,
    config: Any,
    units: list[dict[str, Any]],
    told: list[str],
) -> Any:
    """A local cluster of the workers the command asks for its ``units`` (``processes(config,
    units) -> (workers, why)``: where its env steps slowly), with a notice saying why added to
    ``told``; None (in-process) where it asks for one, or where Dask is not installed."""
    workers, why = module.processes(config, units)
    if workers < 2:
        return None
    try:
        executor = cluster.open_executor(cluster.Where(local_workers=workers))
    except cluster.ClusterError:  # no 'distributed' extra: in-process, as everywhere else
        return None
    told.append(
        f"{parser.prog}: {why}: the {len(units)} units run in {workers} processes "
        f"(--cluster off: here, one after another)"
    )
    return executor


def _run(
    module: ModuleType,
    config: Any,
    units: list[dict[str, Any]],
    store: kept_files.UnitStore | None,
    executor: Any,
    force: bool,
    figure_process: Any = None,
    told: list[str] | None = None,
) -> int:
    started = time.perf_counter()
    if store is None:
        store = kept_files.UnitStore(config.out)
        if store.exists() and not force:
            raise outdir.OutputDirError(
                f"out='{config.out}' holds the units of an interrupted run "
                f"({kept_files.UNITS_DIRECTORY}/): continue it with --resume {config.out}, or "
                f"pass --force to start over"
            )
        store.start(module.NAME, plain(config), (unit["id"] for unit in units))
        done: dict[str, Any] = {}
    else:  # every kept unit checked before any unit runs
        check = (
            functools.partial(module.check_unit, config) if hasattr(module, "check_unit") else None
        )
        done = store.finished(units, module.UNIT_RESULT, force, check)
        print(f"resuming {config.out}: {len(done)} of {len(units)} units done", file=sys.stderr)
    for line in filter(None, told or ()):  # the run is accepted: the notices held until now
        print(line, file=sys.stderr, flush=True)
    if hasattr(module, "describe"):  # what runs (paper's backend, ...), now the run is accepted
        print(module.describe(config), file=sys.stderr, flush=True)
    pending = [unit for unit in units if unit["id"] not in done]
    bar = progress_bar(
        total=sum(work(module, config, unit) for unit in pending),
        desc=f"factorq {module.NAME}",
        unit="unit" if not hasattr(module, "work") else getattr(module, "WORK_UNIT", "step"),
    )
    where, before = "in-process", bar.n
    if executor is None:  # here, one after another, each unit reporting its progress as it goes
        finished: Any = (
            (index, unit_result(module, config, unit, module.run_unit(config, unit, bar.update)))
            for index, unit in enumerate(pending)
        )
    else:
        where = executor.description
        task = functools.partial(run_unit_task, module.__name__, config)
        finished = executor.map(task, pending, [f"{module.NAME}-{u['id']}" for u in pending])
    try:
        for index, result in finished:
            store.keep(pending[index], result)
            done[pending[index]["id"]] = result
            # the unit's whole share, whatever it reported
            bar.update(max(0, before + work(module, config, pending[index]) - bar.n))
            before = bar.n
    finally:
        bar.close()
    outcomes = [done[unit["id"]] for unit in units]
    summary = module.summarise(config, outcomes)
    wall_s, resumed = time.perf_counter() - started, len(units) - len(pending)
    results_dict = envelope(
        module, config, summary, wall_s=wall_s, where=where, units=len(units), resumed=resumed
    )
    paths = write_outputs(module, results_dict, Path(config.out), figure_process)
    if hasattr(module, "finish"):
        paths.update(module.finish(config, outcomes, Path(config.out)))
    store.remove()  # the results are complete: nothing left to resume
    report = report_module(module)
    if hasattr(report, "markdown"):
        print(report.markdown(results_dict))
    for path in paths.values():
        print(path)
    return 0
