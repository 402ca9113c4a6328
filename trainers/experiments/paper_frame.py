"""``factorq paper``'s own frame: mid-run checkpoints (``--checkpoint-every``, ``--resume`` of
the kernel's or the collector's whole state), the figure process started before torch loads, and
shards on Dask (``--cluster``, ``--scheduler``, ``--shard-seeds``). ``paper`` is registered like
every command (``paper.NAME``); ``FRAME`` names this module, which the runner's frame defers to.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from factorq_trainers.experiments import paper
from factorq_trainers.runner import frame, options

if TYPE_CHECKING:
    from factorq_trainers.reports.figure_process import FigureProcess

#: The options of this frame that are not fields of ``PaperConfig``.
FRAME_OPTIONS = ("checkpoint_every", "resume")


def _as_option(message: str) -> str:
    return frame.as_option(message, paper.PaperConfig, FRAME_OPTIONS)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--checkpoint-every``, ``--resume``, ``--force`` and the cluster options."""
    from factorq_trainers.experiments import cluster_runs

    parser.add_argument(
        "--checkpoint-every",
        metavar="EVERY",
        help="Save the run's whole state to OUT/checkpoint/ every EVERY episodes (summed over "
        "all experiments, e.g. 5000) or seconds (e.g. 30s; also 10m, 1h), atomically, keeping "
        "the previous checkpoint too; removed when the run finishes. (default: off)",
        default=argparse.SUPPRESS,
    )
    parser.add_argument(
        "--resume",
        metavar="DIR",
        help="Continue the interrupted run whose --out is DIR from its last checkpoint, with "
        "the config saved there (options repeated must match it; --threads and "
        "--checkpoint-every may change) and the same numbers as an uninterrupted run.",
        default=argparse.SUPPRESS,
    )
    parser.add_argument(
        "--force", action="store_true", default=argparse.SUPPRESS, help=frame.FORCE_HELP
    )
    cluster_runs.add_paper_options(parser)  # --cluster, --scheduler, --shard-seeds


class _Bar:
    """A tqdm progress bar fed by ``paper.run``'s progress reports."""

    def __init__(self) -> None:
        from tqdm import tqdm

        self._tqdm = tqdm
        self.bar: Any = None  # a tqdm bar once the first progress arrives (tqdm: untyped)

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


def main(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    figure_process: FigureProcess | None = None,
) -> int:
    from factorq_trainers.experiments import cluster_runs
    from factorq_trainers.reports import report
    from factorq_trainers.runner import checkpoint, outdir, resources, resume_checks

    resume = None
    try:
        every = getattr(args, "checkpoint_every", None)
        if every is not None:
            every = checkpoint.parse_every(every)
        if hasattr(args, "resume"):
            resume = checkpoint.load(args.resume)
            config = paper.resume_config(
                resume.config, options.given_options(args, paper.PaperConfig), args.resume
            )
            resume_checks.check_checkpoint(resume, config)  # the whole content, before any output
        else:
            config = paper.PaperConfig(**options.given_options(args, paper.PaperConfig))
        backend = paper.resolve_backend(config)
        checkpointing = every is not None or resume is not None
        estimate = resources.paper_estimate(config, checkpointing=checkpointing)
        large = resources.check(estimate, "run", resources.PAPER_HINT)
        executor = cluster_runs.paper_executor(args)  # None: in-process, as always
    except (ValueError, TypeError, NotImplementedError) as error:
        frame.error(parser, _as_option(str(error)))
        return frame.EXIT_USAGE
    if large is not None:
        print(large, file=sys.stderr)
    outputs = (report.RESULTS_FILE, report.FIGURE_FILE, report.REPORT_FILE)
    try:  # the only writer of --out from here on: checked before any work
        with outdir.claim(
            config.out, outputs=outputs, force=hasattr(args, "force"), resume=resume is not None
        ):
            if resume is None:
                checkpoint.check_none_in(config.out)  # under the lock: no live run is writing it
            return _run(parser, args, config, backend, every, resume, executor, figure_process)
    except (outdir.OutputDirError, checkpoint.CheckpointError) as error:
        if executor is not None:
            executor.close()
        frame.error(parser, _as_option(str(error)))
        return frame.EXIT_USAGE


def _run(
    parser: argparse.ArgumentParser,
    args: argparse.Namespace,
    config: paper.PaperConfig,
    backend: str,
    every: Any,
    resume: Any,
    executor: Any,
    figure_process: Any,
) -> int:
    from factorq_trainers.experiments import cluster_runs
    from factorq_trainers.reports import report
    from factorq_trainers.runner import checkpoint

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

        def curves_ready(partial: dict[str, Any]) -> None:  # before the claims: draw meanwhile
            if figure_process is not None:
                report.send_figure(figure_process, partial, config.out)

        if executor is None:
            results = paper.run(
                config,
                progress=bar,
                checkpoint_every=every,
                resume=resume,
                curves_ready=curves_ready,
            )
        else:
            results = cluster_runs.run_paper_on(executor, config, args, progress=bar)
        bar.close()
        paths = report.write_results(results, config.out, figure_process=figure_process)
        checkpoint.remove(config.out)  # the results are complete: nothing left to resume
    except KeyboardInterrupt:
        bar.close()
        kept = f" (resume it with --resume {config.out})" if checkpoint.exists(config.out) else ""
        print(f"{parser.prog}: interrupted{kept}", file=sys.stderr)
        return frame.EXIT_INTERRUPTED
    except (checkpoint.CheckpointError, ValueError) as error:  # incl. the kernel's refusal
        bar.close()
        frame.error(parser, _as_option(str(error)))
        return frame.EXIT_USAGE
    except (OSError, report.FigureError) as error:  # a full disk, a directory that vanished
        bar.close()
        frame.failure(parser, error)
        return frame.EXIT_FAILURE
    wall = results["timing"]["wall_s"]
    print(f"results in {Path(config.out)}/ after {wall:.1f} s:")
    for path in paths.values():
        print(f"  {path}")
    for name, claim in results["claims"].items():
        measured = claim["detail"] if claim["pass"] is None else report.claim_value(claim)
        print(f"{name} {report.verdict(claim):4}  {claim['statement']}: {measured}")
    return 0
