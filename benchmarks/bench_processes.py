"""Child processes for the modular paper run: ``processes.run_each`` (a fresh interpreter per item,
``python -m factorq_trainers.experiments.paper_processes``, work pickled over stdin) against
``concurrent.futures.ProcessPoolExecutor`` with a ``spawn`` and a ``forkserver`` context (issue 24
item 5, issue 29 g).

Measured, each way, in one session, the ways interleaved (``--repeats`` rounds):

- ``start-up``: two items that report once and return at once: the wall time from the call to
  both results (a child's interpreter, its imports, the round trip);
- ``workload``: two algorithms of a small modular paper run (``paper._modular_in_process``, the
  work ``factorq paper --backend modular`` gives its children; ``--episodes``), run side by side:
  the wall time of ``run_each``.

The executor ways are what a port would do: progress batched as ``processes`` batches it, through
a ``multiprocessing`` queue given to each worker by its initializer, the worker ignoring SIGINT
(set in the initializer), one worker per item. ``forkserver`` preloads torch and the paper module
in its server, so each child forks from an interpreter that has them. Run from the repository root:

    .venv/bin/python benchmarks/bench_processes.py
    .venv/bin/python benchmarks/bench_processes.py --repeats 5 --episodes 20

Timings are never asserted anywhere.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import multiprocessing
import queue
import signal
import statistics
import time
from dataclasses import replace
from typing import Any

from factorq_trainers.experiments import paper
from factorq_trainers.experiments import paper_processes as processes

_PROGRESS: Any = None


class _Batched:
    """``report`` in a worker: tallies sent at most every ``PROGRESS_SECONDS`` (as
    ``processes._Reporter`` does over its pipe)."""

    def __init__(self) -> None:
        self.episodes = self.experiments = 0
        self.sent = time.monotonic()

    def __call__(self, episodes: int, experiments: int) -> None:
        self.episodes += int(episodes)
        self.experiments += int(experiments)
        if time.monotonic() - self.sent >= processes.PROGRESS_SECONDS:
            self.flush()

    def flush(self) -> None:
        if self.episodes or self.experiments:
            _PROGRESS.put((self.episodes, self.experiments))
            self.episodes = self.experiments = 0
        self.sent = time.monotonic()


def _initializer(progress_queue: Any) -> None:
    global _PROGRESS
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _PROGRESS = progress_queue


def _in_worker(work: Any, args: tuple[Any, ...]) -> Any:
    report = _Batched()
    result = work(*args, report)
    report.flush()
    return result


def run_each_pool(kind: str, work: Any, items: dict[str, tuple[Any, ...]], progress: Any) -> Any:
    """``processes.run_each`` on a ProcessPoolExecutor of ``kind`` (its results, in order)."""
    context = multiprocessing.get_context(kind)
    if kind == "forkserver":
        context.set_forkserver_preload(["torch", "factorq_trainers.experiments.paper"])
    progress_queue = context.Queue()
    with concurrent.futures.ProcessPoolExecutor(
        max_workers=len(items),
        mp_context=context,
        initializer=_initializer,
        initargs=(progress_queue,),
    ) as pool:
        futures = {name: pool.submit(_in_worker, work, args) for name, args in items.items()}
        pending = set(futures.values())
        while pending:
            _, pending = concurrent.futures.wait(pending, timeout=processes.PROGRESS_SECONDS)
            while True:
                try:
                    progress(*progress_queue.get_nowait())
                except queue.Empty:
                    break
        return {name: future.result() for name, future in futures.items()}


def quick(tag: str, report: Any) -> str:
    """Start-up work: report once, return."""
    report(1, 0)
    return tag


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--episodes", type=int, default=10)
    options = parser.parse_args()
    import bench_processes as me  # by its module name: a child imports what it runs

    config = replace(
        paper.PaperConfig(seeds=4, runs=2, episodes=options.episodes, size=6, obstacles=4),
        threads=1,
        backend="modular",
        out="unused",
    )
    ways = {
        "run_each (python -m)": lambda work, items: processes.run_each(work, items, _ignore),
        "executor, spawn": lambda work, items: me.run_each_pool("spawn", work, items, _ignore),
        "executor, forkserver": lambda w, items: me.run_each_pool("forkserver", w, items, _ignore),
    }
    timings: dict[str, dict[str, list[float]]] = {way: {"start": [], "work"
                                                        : []} for way in ways}  # fmt: skip
    reference = None
    for _ in range(options.repeats):
        for way, run in ways.items():
            started = time.perf_counter()
            assert run(me.quick, {"a": ("a",), "b": ("b",)}) == {"a": "a", "b": "b"}
            timings[way]["start"].append(time.perf_counter() - started)
            started = time.perf_counter()
            items = {algorithm: (config, algorithm) for algorithm in config.algorithms}
            metrics = run(paper._modular_in_process, items)
            timings[way]["work"].append(time.perf_counter() - started)
            digest = {k: {n: a.tobytes() for n, a in v.items()} for k, v in metrics.items()}
            assert reference is None or digest == reference, f"{way}: other numbers"
            reference = digest
    print(f"{'way':24} {'start-up s (median, all)':34} {'workload s (median, all)'}")
    for way, times in timings.items():
        start, work = times["start"], times["work"]
        print(
            f"{way:24} {statistics.median(start):6.2f} {[round(t, 2) for t in start]!s:27} "
            f"{statistics.median(work):6.2f} {[round(t, 2) for t in work]}"
        )


def _ignore(*counts: int) -> None:
    pass


if __name__ == "__main__":
    main()
