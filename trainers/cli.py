"""The ``factorq`` command: one subcommand per registered command (``runner.registry``), its
options the fields of its ``CONFIG``, run by ``runner.frame``; plus ``factorq report DIR`` and
``factorq sweep``. A command imports only what it runs (``factorq paper`` starts without
torchrl); one that declares ``FIGURE_PROCESS`` starts its figure process before torch loads
(docs/decisions.md, "``factorq paper`` end to end")."""

from __future__ import annotations

import argparse
import atexit
import contextlib
import gc
import importlib
import os
import sys
import threading
import typing
from typing import TYPE_CHECKING

from factorq_trainers.runner import frame, options, registry
from factorq_trainers.runner.frame import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_USAGE, Parser

if TYPE_CHECKING:
    from factorq_trainers.commands.paper.figure_process import FigureProcess

__all__ = ["EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_USAGE", "build_parser", "main"]


def build_parser(
    *, compare_options: bool = True, command: str | None = None
) -> argparse.ArgumentParser:
    """The ``factorq`` parser. ``command``: the command being run; only its module is imported
    (its options added), every other command is listed by name and help alone.
    ``compare_options=False`` leaves the options of ``compare`` out (they need torchrl)."""
    parser = Parser(
        prog="factorq",
        description="Factor-Q for torchrl: reproduce the paper's experiment and its report.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)
    for name, entry in registry.commands().items():
        wanted = (command is None or command == name) and (compare_options or name != "compare")
        if not wanted:
            commands.add_parser(name, help=entry.help)
            continue
        module = registry.load(name)
        sub = commands.add_parser(
            name, help=entry.help, description=getattr(module, "DESCRIPTION", entry.help)
        )
        options.add_options(sub, module.CONFIG)
        frame.add_frame_options(sub)
        sub.set_defaults(module=module, command_parser=sub)
    report_parser = commands.add_parser(
        "report",
        help="redraw the figure and Markdown of any command's results directory",
        description="Regenerate the figure and the Markdown report of the results in "
        "RESULTS_DIR (results.json of factorq paper, comparison.json, dependencies.json, ... of "
        "the other commands) from the results file alone.",
    )
    report_parser.add_argument("results_dir", metavar="RESULTS_DIR", help="a command's --out")
    report_parser.set_defaults(module=None, command_parser=report_parser)
    sweep_help = "run a grid of a command's configurations, in-process or on a Dask cluster"
    commands.add_parser("sweep", help=sweep_help, add_help=False)  # main hands it to sweep
    return parser


def _report(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from factorq_trainers import reports

    try:
        paths = reports.regenerate(args.results_dir)
    except (FileNotFoundError, ValueError, KeyError) as problem:
        message = f"missing field {problem}" if isinstance(problem, KeyError) else str(problem)
        frame.error(parser, message)
        return EXIT_USAGE
    except frame.results.FigureError as problem:
        frame.failure(parser, problem)
        return EXIT_FAILURE
    for path in paths.values():
        print(path)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run ``factorq`` with ``argv`` (default: the command line); return the exit status.
    Without ``argv`` the process is the command's own: modules load with the garbage collector
    paused, then ``gc.freeze``, and a command ends with ``_exit``."""
    command_line = argv is None
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["sweep"]:
        from factorq_trainers.distributed import sweep

        return sweep.main(argv[1:])
    command = argv[0] if argv and argv[0] in (*registry.commands(), *registry.BUILT_IN) else None
    figure_process = None
    # (``report`` is built in: no entry, no figure process)
    entry = registry.commands().get(command) if command is not None else None
    if entry is not None and entry.figure_process and not {"-h", "--help"} & set(argv):
        # First, before torch loads: the helper loads matplotlib on the other core meanwhile.
        package = entry.module.rpartition(".")[0]
        figure_process = importlib.import_module(f"{package}.figure_process").FigureProcess.start()
    try:
        code = _main(argv, command, command_line, figure_process)
    finally:
        if figure_process is not None:
            figure_process.close()
    if command_line and command is not None:
        _exit(code)
    return code


def _main(
    argv: list[str],
    command: str | None,
    command_line: bool,
    figure_process: FigureProcess | None,
) -> int:
    paused = command_line and gc.isenabled()
    if paused:  # loading creates objects that live as long as the process: nothing to collect
        gc.disable()
    try:
        parser = build_parser(compare_options=command == "compare", command=command)
        if command in registry.commands():  # what it runs besides its module (not ``report``)
            import tqdm  # noqa: F401

            importlib.import_module(registry.commands()[command].report)
    except KeyboardInterrupt:  # while torch loads: nothing started, nothing written
        print(f"factorq{' ' + command if command else ''}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if paused:
            gc.freeze()  # later collections skip everything loaded so far
            gc.enable()
    try:
        args, unknown = parser.parse_known_args(argv)
        if unknown:  # reported by the command's parser: "factorq paper: error: ..."
            getattr(args, "command_parser", parser).error(
                f"unrecognized arguments: {' '.join(unknown)}"
            )
    except SystemExit as exit_:  # --help, or a malformed option (argparse printed why)
        return exit_.code if isinstance(exit_.code, int) else EXIT_USAGE
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:  # the parsed command in the runner's frame (``report`` redraws files instead)
        if args.module is None:
            return _report(args.command_parser, args)
        return frame.execute(args.module, args.command_parser, args, figure_process)
    except KeyboardInterrupt:  # outside the run itself (validation, imports): nothing written
        print(f"{args.command_parser.prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _exit(code: int) -> typing.NoReturn:
    """End the process with ``code`` once the atexit handlers ran and the output is flushed,
    skipping the interpreter's teardown (freeing every module's objects: 0.1-0.4 s with torch).
    Exits normally instead if a thread other than the fast path's pool workers (idle once a run
    is over) still runs: it may have work to finish."""
    others = [
        thread
        for thread in threading.enumerate()
        if thread is not threading.main_thread()
        and not thread.daemon
        and not thread.name.startswith("factorq-fast")
    ]
    if others:
        sys.exit(code)
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError, ValueError):
                stream.flush()
        os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
