"""``factorq compare``'s own frame: checkpoints after every method and, with
``--checkpoint-every``, of the running method's whole state (``runner.compare_checkpoint``),
resumed mid-method; one task per method on Dask. ``compare`` is registered like every command
(``compare.NAME``); ``FRAME`` names this module, which the runner's frame defers to.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from typing import Any

from factorq_trainers.experiments import compare
from factorq_trainers.runner import cluster, frame

RESUME_NAMES = ("checkpoint_every", "resume")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``--force``, ``--checkpoint-every``, ``--resume`` and the cluster options."""
    cluster.add_options(parser)
    parser.add_argument(
        "--force", action="store_true", default=argparse.SUPPRESS, help=frame.FORCE_HELP
    )
    parser.add_argument(
        "--checkpoint-every",
        metavar="EVERY",
        help="Also save the running method's whole state (tables or networks, optimiser, "
        "replay buffer, random state, world, records) to OUT/checkpoint/ every EVERY "
        "episodes (summed over the method's experiments, e.g. 500) or seconds (e.g. 30s; "
        "also 10m, 1h), atomically: --resume then continues it mid-method. (default: off: "
        "a checkpoint after each method only)",
        default=argparse.SUPPRESS,
    )
    parser.add_argument(
        "--resume",
        metavar="DIR",
        help="Continue the interrupted comparison whose --out is DIR: the methods it had "
        "finished (saved to DIR/checkpoint/ after each one) are not rerun, the one it was "
        "saved during continues from its state (with --checkpoint-every) or its start, "
        "with the same numbers as an uninterrupted run (options repeated must match; "
        "--threads and --checkpoint-every may change).",
        default=argparse.SUPPRESS,
    )


def main(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    """Run ``factorq compare`` with the parsed ``args``; the exit status."""
    from factorq_trainers.experiments import cluster_runs
    from factorq_trainers.reports import compare_report
    from factorq_trainers.runner import checkpoint, options, outdir, resources

    resume = None
    try:
        every = getattr(args, "checkpoint_every", None)
        if every is not None:
            every = checkpoint.parse_every(every)
        given = options.given_options(args, compare.CompareConfig)
        if hasattr(args, "resume"):
            resume = compare.load_checkpoint(args.resume)
            config = compare.resume_config(resume.config, given, args.resume)
            # checked before its progress line is printed (on a copy: the run checks the
            # original again, converting its traces as it goes)
            compare.check_checkpoint(resume._replace(finished=dict(resume.finished)), config)
        else:
            config = compare.CompareConfig(**given)
        checkpointing = every is not None or (resume is not None and resume.every is not None)
        large = resources.check(
            resources.compare_estimate(config, checkpointing=checkpointing),
            "comparison",
            resources.COMPARE_HINT,
        )
        executor = cluster.executor_from_args(args)  # None: in-process, as always
        if executor is not None and (resume is not None or every is not None):
            executor.close()
            what = "resume" if resume is not None else "checkpoint_every"
            raise ValueError(
                f"{what} does not apply to a run on a cluster: rerun it there (each method is "
                f"one task), or run without --cluster and --scheduler"
            )
    except (ValueError, TypeError) as error:
        frame.error(parser, frame.as_option(str(error), compare.CompareConfig, RESUME_NAMES))
        return frame.EXIT_USAGE
    if large is not None:
        print(large, file=sys.stderr)
    bars: dict[str, Any] = {}

    def progress(method: str, done: int, total: int) -> None:
        from tqdm.auto import tqdm

        if method not in bars:
            bars[method] = tqdm(total=total, desc=f"factorq compare {method}", unit="step")
        bar = bars[method]
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    outputs = (*compare_report.OUTPUT_FILES, compare_report.LOGS_DIRECTORY)
    try:
        with outdir.claim(
            config.out, outputs=outputs, force=hasattr(args, "force"), resume=resume is not None
        ):
            if resume is not None:
                print(f"resuming {args.resume} ({resume.progress})", file=sys.stderr)
            print(
                f"{len(config.methods)} methods x {len(config.worlds)} worlds x {config.seeds} "
                f"seeds, {config.steps:,} env steps each",
                file=sys.stderr,
            )
            # Logs are written from the traces when the run is over, beside the other outputs
            # and renamed into place with them: one run's logs, never appended to another's.
            logs = compare_report.staging_logs(config.out)
            try:
                if executor is None:  # checkpoints after every method: a kill loses one at most
                    results = compare.run(
                        config,
                        progress,
                        logs_dir=logs,
                        checkpoints=True,
                        resume=resume,
                        checkpoint_every=every,
                    )
                else:  # one task per method

                    def summarise(
                        config: compare.CompareConfig, runs: dict[str, Any]
                    ) -> dict[str, Any]:
                        compare.write_logs(config, runs, logs)
                        return compare.summarise(config, runs)

                    results = cluster_runs.run_compare_on(
                        executor, config, compare.run_method, summarise
                    )
                paths = compare_report.write_outputs(results, config.out, logs=logs)
                checkpoint.remove(config.out)  # the outputs are complete: nothing to resume
            finally:
                shutil.rmtree(logs, ignore_errors=True)  # renamed away unless the run failed
    except (outdir.OutputDirError, checkpoint.CheckpointError) as error:
        if executor is not None:
            executor.close()
        frame.error(parser, frame.as_option(str(error), compare.CompareConfig, RESUME_NAMES))
        return frame.EXIT_USAGE
    except KeyboardInterrupt:
        kept = f" (resume it with --resume {config.out})" if checkpoint.exists(config.out) else ""
        print(f"{parser.prog}: interrupted{kept}", file=sys.stderr)
        return frame.EXIT_INTERRUPTED
    except OSError as error:  # a full disk, a directory that vanished: say so in one line
        frame.failure(parser, error)
        return frame.EXIT_FAILURE
    print(compare_report.report_markdown(results))
    for path in paths.values():
        print(path)
    return 0
