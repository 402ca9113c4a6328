"""The ``factorq`` command: reproduce the paper (``factorq paper``), redraw its report
(``factorq report RESULTS_DIR``)."""

from __future__ import annotations

import argparse
import re
import sys
import types
import typing
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

from trainers import checkpoint, paper, sweep

EXIT_FAILURE = 1
EXIT_USAGE = 2
COMPARE_HELP = "compare tabular Factor-Q, Q-learning, DQN and neural Factor-Q on the three worlds"
EXIT_INTERRUPTED = 130  # 128 + SIGINT, what shells report for Ctrl-C
_LIST_FIELDS = {"worlds": paper.WORLDS, "algorithms": paper.ALGORITHMS}


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line: ``factorq paper: error: ...`` (exit 2)."""

    def error(self, message: str) -> typing.NoReturn:
        _error(self, message)
        raise SystemExit(EXIT_USAGE)


def _error(parser: argparse.ArgumentParser, message: str) -> None:
    print(f"{parser.prog}: error: {message} (see {parser.prog} --help)", file=sys.stderr)


def _option(name: str) -> str:
    return "--" + name.replace("_", "-")


def _value_type(annotation: Any) -> type:
    """``int``, ``float`` or ``str`` from a field's annotation (``int | None`` -> ``int``)."""
    if isinstance(annotation, types.UnionType):
        annotation = next(arg for arg in typing.get_args(annotation) if arg is not type(None))
    return annotation if annotation in (int, float, str) else str


def _add_config_options(parser: argparse.ArgumentParser) -> None:
    """One option per ``PaperConfig`` field, its help the field's docstring."""
    docs = paper.field_docs(paper.PaperConfig)
    annotations = typing.get_type_hints(paper.PaperConfig)
    for field in fields(paper.PaperConfig):
        default = field.default if field.default is not MISSING else None
        help_text = docs.get(field.name, "")
        if field.name in _LIST_FIELDS:
            shown = ",".join(default)
            parser.add_argument(
                _option(field.name),
                action="append",
                metavar="NAME[,NAME]",
                help=f"{help_text} Repeatable. (default: {shown})",
                default=argparse.SUPPRESS,
            )
            continue
        kwargs: dict[str, Any] = {}
        if field.name == "backend":
            kwargs["choices"] = paper.BACKENDS
        parser.add_argument(
            _option(field.name),
            type=_value_type(annotations[field.name]),
            metavar=field.name.upper(),
            help=f"{help_text} (default: {'auto' if default is None else default})",
            default=argparse.SUPPRESS,
            **kwargs,
        )


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="factorq",
        description="Factor-Q for torchrl: reproduce the paper's experiment and its report.",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    paper_parser = commands.add_parser(
        "paper",
        help="run the paper's experiment (3 worlds x 2 algorithms, many seeds) and report it",
        description="Run the paper's experiment (SPEC section 4) over many seeds and write "
        "results.json, figure3.png and report.md to --out.",
    )
    _add_config_options(paper_parser)
    paper_parser.add_argument(
        "--checkpoint-every",
        metavar="EVERY",
        help="Save the run's whole state to OUT/checkpoint/ every EVERY episodes (summed over all "
        "experiments, e.g. 5000) or seconds (e.g. 30s; also 10m, 1h), atomically, keeping the "
        "previous checkpoint too; removed when the run finishes. (default: off)",
        default=argparse.SUPPRESS,
    )
    paper_parser.add_argument(
        "--resume",
        metavar="DIR",
        help="Continue the interrupted run whose --out is DIR from its last checkpoint, with the "
        "config saved there (options repeated must match it; --threads and --checkpoint-every "
        "may change) and the same numbers as an uninterrupted run.",
        default=argparse.SUPPRESS,
    )
    sweep.add_paper_options(paper_parser)  # --cluster, --scheduler, --shard-seeds
    paper_parser.set_defaults(handler=_paper, command_parser=paper_parser)
    report_parser = commands.add_parser(
        "report",
        help="redraw figure3.png and report.md from a results directory",
        description="Regenerate figure3.png and report.md from RESULTS_DIR/results.json alone.",
    )
    report_parser.add_argument("results_dir", metavar="RESULTS_DIR", help="a `factorq paper` --out")
    report_parser.set_defaults(handler=_report, command_parser=report_parser)
    # `main` hands `factorq compare ...` to trainers.compare before parsing, so that torchrl (which
    # DQN needs) is imported only for that command; this entry lists it in `factorq --help`.
    commands.add_parser("compare", help=COMPARE_HELP, add_help=False)
    commands.add_parser("sweep", help=sweep.HELP, add_help=False)  # main hands it to trainers.sweep
    return parser


def _given_options(args: argparse.Namespace) -> dict[str, Any]:
    """The config fields given on the command line (field name -> value)."""
    values = {
        field.name: getattr(args, field.name)
        for field in fields(paper.PaperConfig)
        if hasattr(args, field.name)
    }
    for name in _LIST_FIELDS:
        if name in values:  # repeated and/or comma-separated
            values[name] = [item for given in values[name] for item in given.split(",")]
    return values


def _config_from_args(args: argparse.Namespace) -> paper.PaperConfig:
    """A validated config from the parsed options (ValueError/TypeError when invalid)."""
    return paper.PaperConfig(**_given_options(args))


def _as_option(message: str) -> str:
    """``seeds=0 is out of range`` -> ``--seeds=0 is out of range`` (the names the user typed):
    a leading ``name:`` and every ``name=`` of an option."""
    names = {field.name for field in fields(paper.PaperConfig)} | {"checkpoint_every", "resume"}
    message = re.sub(
        r"^(\w+)(?=:)", lambda m: _option(m[1]) if m[1] in names else m[1], message, count=1
    )
    return re.sub(
        r"(?<![\w.'-])(\w+)(?==)", lambda m: _option(m[1]) if m[1] in names else m[1], message
    )


class _Bar:
    """A tqdm progress bar fed by ``paper.run``'s progress reports."""

    def __init__(self) -> None:
        from tqdm import tqdm

        self._tqdm = tqdm
        self.bar = None

    def __call__(self, progress: paper.Progress) -> None:
        if self.bar is None:
            self.bar = self._tqdm(
                total=progress.episodes_total,
                initial=progress.episodes_completed,  # a resumed run starts part way
                desc="factorq paper",
                unit="episode",
                unit_scale=True,
                dynamic_ncols=True,
                mininterval=0.5 if sys.stderr.isatty() else 30.0,  # tidy logs when redirected
                file=sys.stderr,
            )
        self.bar.update(progress.episodes_completed - self.bar.n)
        self.bar.set_postfix_str(
            f"experiments {progress.experiments_finished}/{progress.experiments_total}",
            refresh=False,
        )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _paper(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    resume = None
    try:
        every = getattr(args, "checkpoint_every", None)
        if every is not None:
            every = checkpoint.parse_every(every)
        if hasattr(args, "resume"):
            resume = checkpoint.load(args.resume)
            config = paper.resume_config(resume.config, _given_options(args), args.resume)
        else:
            config = _config_from_args(args)
            checkpoint.check_none_in(config.out)
        backend = paper.resolve_backend(config)
        paper.backend_driver(backend)
        executor = sweep.paper_executor(args)  # None: in-process, as always
    except (ValueError, TypeError, NotImplementedError) as error:
        _error(parser, _as_option(str(error)))
        return EXIT_USAGE
    bar = _Bar()
    try:
        if resume is not None:
            print(
                f"resuming {args.resume} from {resume.path.name} of {resume.saved_utc} "
                f"({resume.episodes_completed} episodes done)",
                file=sys.stderr,
            )
        print(
            f"{len(config.cells) * config.seeds} experiments ({config.seeds} seeds x "
            f"{len(config.worlds)} worlds x {len(config.algorithms)} algorithms), "
            f"{config.runs} runs x {config.episodes} episodes each, {backend} backend",
            file=sys.stderr,
        )
        if executor is None:
            results = paper.run(config, progress=bar, checkpoint_every=every, resume=resume)
        else:
            results = sweep.run_paper_on(executor, config, args, progress=bar)
        bar.close()
        paths = paper.write_results(results, config.out)
        checkpoint.remove(config.out)  # the results are complete: nothing left to resume
    except KeyboardInterrupt:
        bar.close()
        kept = f" (resume it with --resume {config.out})" if checkpoint.exists(config.out) else ""
        print(f"{parser.prog}: interrupted{kept}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except checkpoint.CheckpointError as error:
        bar.close()
        _error(parser, _as_option(str(error)))
        return EXIT_USAGE
    except OSError as error:  # a full disk, a directory that vanished: say so in one line
        bar.close()
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return EXIT_FAILURE
    from trainers.report import claim_value, verdict

    wall = results["timing"]["wall_s"]
    print(f"results in {Path(config.out)}/ after {wall:.1f} s:")
    for path in paths.values():
        print(f"  {path}")
    for name, claim in results["claims"].items():
        measured = claim["detail"] if claim["pass"] is None else claim_value(claim)
        print(f"{name} {verdict(claim):4}  {claim['statement']}: {measured}")
    return 0


def _report(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from trainers import report

    try:
        paths = report.regenerate(args.results_dir)
    except (FileNotFoundError, ValueError, KeyError) as error:
        message = f"missing field {error}" if isinstance(error, KeyError) else str(error)
        _error(parser, message)
        return EXIT_USAGE
    for path in paths.values():
        print(path)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run ``factorq`` with ``argv`` (default: the command line); return the exit status."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["sweep"]:
        return sweep.main(argv[1:])
    if argv[:1] == ["compare"]:
        from trainers import compare

        try:
            return compare.main(argv[1:])
        except KeyboardInterrupt:
            print("factorq compare: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exit_:  # --help, or a malformed option (argparse printed why)
        return exit_.code if isinstance(exit_.code, int) else EXIT_USAGE
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        return args.handler(args.command_parser, args)
    except KeyboardInterrupt:  # outside the run itself (validation, imports): nothing written
        print(f"{args.command_parser.prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
