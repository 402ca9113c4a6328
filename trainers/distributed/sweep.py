"""``factorq sweep``: a grid (or list) of a command's configurations (``paper`` by default),
each with its seeds, run in-process or on a Dask cluster, one task per configuration, each kept
in ``OUT/configs/<digest>.json`` as it finishes, gathered into ``sweep.json``, ``sweep.md`` and
one figure per swept axis.

This module is the command line (options over the sweep file, the memory estimate, the claim of
``--out``, the progress bar) and the run (``run_sweep``): every configuration run whole
(``frame.run_in_process``) as one task on an executor, its results dict kept in
``OUT/configs/<digest>.json`` (sealed and tied by ``kept``) as it finishes, then ``sweep.json``'s
dict gathered from those files, each configuration's cells taken by its command's
``sweep_cells``. ``sweep_spec`` reads and checks the sweep file (its format is there),
``factorq_trainers.reports.sweep`` draws ``sweep.md`` and the figures.

A configuration whose kept file passes its checks is not run again, so a killed sweep continues
where it stopped, and a sweep that adds axis values runs only the new configurations. A
configuration's numbers depend on it alone: a sweep's are the same in-process, on any number of
workers and after any number of interruptions.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import time
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from factorq_trainers.distributed import sweep_spec
from factorq_trainers.distributed.sweep_spec import SweepError, SweepSpec, read_spec_file
from factorq_trainers.reports import sweep as sweep_report
from factorq_trainers.runner import cluster, frame, kept, outdir, registry, resources
from factorq_trainers.runner import results as result_files
from factorq_trainers.runner.frame import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE, progress_bar


def config_result_path(directory: str | os.PathLike, config: Any) -> Path:
    """``directory/<digest>.json``: where a configuration's results are kept."""
    return Path(directory) / f"{sweep_spec.config_digest(config)}.json"


#: What ``kept`` calls a kept configuration result in its messages.
CONFIG_FILE = "configuration file"


def _read_config_result(path: Path, command: str, config: Any) -> dict[str, Any]:
    """The results of ``command`` for ``config`` kept at ``path``: sealed, kept for this command
    and configuration, values checked (a ValueError naming it otherwise)."""
    check = getattr(sweep_spec._reports_of(command), "results_problem", None)  # its own check
    return kept.read_sealed(
        path, CONFIG_FILE, kept_for=kept.tie(command, sweep_spec.config_digest(config)), check=check
    )


def _pending_configs(
    directory: Path, configs: Sequence[Any], force: bool, command: str
) -> list[Any]:
    """The configurations of ``configs`` to run: those without a kept result, and (``force``)
    those whose kept result fails its checks; without ``force`` such a file is refused."""
    return [
        config
        for config in configs
        if not kept.reusable(
            config_result_path(directory, config),
            functools.partial(_read_config_result, command=command, config=config),
            force,
        )
    ]


def _gathered(
    spec: SweepSpec,
    pending: list,
    started: float,
    executor: cluster.InProcess | cluster.DaskExecutor,
) -> dict[str, Any]:
    """``sweep.json``'s dict: one row per configuration read back from ``OUT/configs/``;
    ``pending``: the configurations run now."""
    computed = time.perf_counter() - started
    command, reports = spec.command, sweep_spec._reports_of(spec.command)
    directory = Path(spec.out) / sweep_spec.CONFIGS_DIRECTORY
    configs = spec.configurations()
    rows = []
    for config, point in zip(configs, spec.points(), strict=True):
        path = config_result_path(directory, config)
        results = _read_config_result(path, command, config)  # digest, tie, values checked
        try:  # a kept file is the user's: it may have been edited or cut short
            cells_of = reports.sweep_cells(results)
        except (ValueError, KeyError, TypeError, AttributeError, IndexError) as error:
            raise ValueError(
                f"configuration file {path} is not a factorq {command} result ({error!r}): "
                f"{kept.REMEDY}"
            ) from None
        rows.append(
            {
                "values": point,
                "digest": sweep_spec.config_digest(config),
                "config": frame.plain(config),
                "results_file": f"{sweep_spec.CONFIGS_DIRECTORY}/{path.name}",
                "cells": cells_of,
                "claims": {  # the paper's claims, where the command has them
                    name: {key: claim[key] for key in ("value", "ci95", "pass")}
                    for name, claim in results.get("claims", {}).items()
                },
            }
        )
    return {
        "command": command,
        "measures": list(reports.SWEEP_MEASURES),
        "axes": spec.axes,
        "base": frame.plain(dict(spec.base)),
        "seeds": spec.seeds,
        "configurations": frame.plain(rows),
        "timing": {
            "wall_s": round(time.perf_counter() - started, 3),
            "compute_s": round(computed, 3),
            "where": executor.description,
            "configurations_total": len(configs),
            "configurations_run_now": len(pending),
        },
        "software": result_files.software_versions(),
    }


def _units_task(command: str, config: Any) -> dict[str, Any]:
    return frame.run_in_process(registry.load(command), config)


def run_sweep(
    spec: SweepSpec,
    executor: cluster.InProcess | cluster.DaskExecutor,
    progress: Callable[[int, int], None] | None = None,
    force: bool = False,
) -> dict[str, Any]:
    """Run and keep every configuration of ``spec`` not already kept, then gather ``sweep.json``'s
    dict. ``progress(done, total)`` counts configurations (those found on disk are done from the
    start). A kept file that fails its checks is refused before any work, or with ``force``
    recomputed."""
    started = time.perf_counter()
    directory = Path(spec.out) / sweep_spec.CONFIGS_DIRECTORY
    configs = spec.configurations()
    pending = _pending_configs(directory, configs, force, spec.command)
    done = len(configs) - len(pending)
    progress = progress or (lambda done, total: None)
    progress(done, len(configs))
    names = [f"{spec.command}-{sweep_spec.config_digest(config)}" for config in pending]
    task = functools.partial(_units_task, spec.command)
    for index, results in executor.map(task, pending, names):
        directory.mkdir(parents=True, exist_ok=True)
        kept_for = kept.tie(spec.command, sweep_spec.config_digest(pending[index]))
        kept.write_sealed(config_result_path(directory, pending[index]), results, kept_for)
        done += 1
        progress(done, len(configs))
    return _gathered(spec, pending, started, executor)


# --------------------------------------------------------------------------------------------
# The command line


def build_parser() -> argparse.ArgumentParser:
    parser = frame.Parser(
        prog="factorq sweep",
        description="Run a grid of `factorq paper` configurations (or, with --command, of "
        "another command's), each with --seeds seeds; write sweep.json, sweep.md and a figure "
        "per axis to --out. Finished configurations are kept in OUT/configs/ and not rerun (a "
        "killed sweep resumes).",
    )
    parser.add_argument("spec", nargs="?", metavar="SPEC", help="a .toml (or .yaml) sweep file")
    parser.add_argument("--command", metavar="NAME", default=argparse.SUPPRESS,
                        help="Whose configs to sweep: paper, compare or any other command "
                        "(dependencies, minigrid, ...), each configuration one task. "
                        "(default: the file's command, else paper)")  # fmt: skip
    parser.add_argument("--grid", action="append", metavar="FIELD=V1,V2", default=[],
                        help="A swept axis: a field of the --command's config and its values "
                        "(repeatable; crossed).")  # fmt: skip
    parser.add_argument("--set", action="append", metavar="FIELD=VALUE", default=[],
                        help="A base value shared by every configuration "
                        "(repeatable).")  # fmt: skip
    parser.add_argument("--seeds", type=int, metavar="N", default=argparse.SUPPRESS,
                        help="Seeds per configuration. "
                        f"(default: {sweep_spec.DEFAULT_SEEDS})")  # fmt: skip
    parser.add_argument("--out", metavar="DIR", default=argparse.SUPPRESS,
                        help=f"Output directory. (default: {sweep_spec.DEFAULT_OUT})")  # fmt: skip
    parser.add_argument("--force", action="store_true",
                        help="Replace the sweep.json and sweep.md of an earlier sweep in --out, "
                        "and recompute any finished configuration whose kept file fails its "
                        "checks (edited, damaged); good ones are reused either way. Without it, "
                        "an --out holding them is refused.")  # fmt: skip
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
    source = args.spec or "options"
    data = dict(sweep_spec.checked_document(read_spec_file(args.spec) if args.spec else {}, source))
    if hasattr(args, "command"):
        data["command"] = args.command
    command = sweep_spec.check_command(data.get("command", "paper"), source)
    base, grid = dict(data.get("base", {})), dict(data.get("grid", {}))
    for name, text in _pairs(args.set, "--set"):
        base[name] = sweep_spec.parse_value(name, text, command)
    for name, text in _pairs(args.grid, "--grid"):
        annotation = sweep_spec.sweepable_fields(command).get(name)
        if typing.get_origin(annotation) is tuple:  # one name per value: regimes=static,dynamic
            grid[name] = [[item] for item in text.split(",") if item]
        else:
            grid[name] = [
                sweep_spec.parse_value(name, item, command) for item in text.split(",") if item
            ]
    if base:
        data["base"] = base
    if grid:
        data["grid"] = grid
    for key in ("seeds", "out"):
        if hasattr(args, key):
            data[key] = getattr(args, key)
    if not data.get("grid") and data.get("configs", [{}]) == [{}]:
        raise SweepError("nothing to sweep: give a sweep file, or --grid FIELD=V1,V2")
    return sweep_spec.spec_from_mapping(data, source)


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
        module = registry.load(spec.command)
        none = resources.Estimate({}, 0, exact_steps=False)  # a command without an estimate
        estimate_of = getattr(module, "estimate", lambda config: none)
        configs = spec.configurations()  # a worker runs one configuration at a time:
        estimate = resources.tasks_estimate([estimate_of(c) for c in configs], workers)
        hint = getattr(module, "HINT", "use fewer --seeds or smaller configurations")
        hint += ", or fewer --cluster workers" if workers > 1 else ""
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
            return _run_sweep_command(parser, spec, executor, args.force)
    except outdir.OutputDirError as error:
        executor.close()
        print(f"{parser.prog}: error: {str(error).replace('out=', '--out=')}", file=sys.stderr)
        return EXIT_USAGE


def _run_sweep_command(
    parser: argparse.ArgumentParser, spec: SweepSpec, executor: Any, force: bool = False
) -> int:
    configs = spec.configurations()
    work = f"{len(configs)} configuration tasks (factorq {spec.command})"
    print(
        f"{len(configs)} configurations x {spec.seeds} seeds = {work}, {executor.description}",
        file=sys.stderr,
    )
    bar: list[Any] = []  # made at the first count, which says how many were done before

    def progress(done: int, total: int) -> None:
        if not bar:
            bar.append(
                progress_bar(total=total, initial=done, desc="factorq sweep", unit="configuration")
            )
        bar[0].update(done - bar[0].n)

    try:
        try:
            sweep = run_sweep(spec, executor, progress, force)
        finally:
            for made in bar:
                made.close()
        paths = sweep_report.write_outputs(sweep, spec.out)
    except KeyboardInterrupt:
        print(f"{parser.prog}: interrupted (run it again to resume)", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (OSError, ValueError) as error:  # a full disk; a kept result file gone bad
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        executor.close()
    print(f"sweep in {Path(spec.out)}/ after {sweep['timing']['wall_s']:.1f} s:")
    for path in paths.values():
        print(f"  {path}")
    return 0
