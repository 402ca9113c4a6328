"""Wall time of a sweep in-process and on a 2-worker Dask ``LocalCluster``, and the scaling
efficiency.

The sweep: 16 configurations (obstacles 5, 10, 15, 20 x eta 0.05, 0.1, 0.2, 0.4) x 100 seeds of the
paper's experiment (3 worlds x 2 algorithms x 10 runs x 200 episodes; ``--episodes`` to shrink it),
one task per configuration. Measured, each into a fresh directory:

- ``in-process, 1 thread``: ``run_sweep`` with ``InProcess`` and ``threads=1``: the work of one
  worker, the baseline of the scaling efficiency;
- ``in-process, 2 threads``: the same with the fast backend's own 2-thread pool (the best one
  process does on 2 cores);
- ``local cluster, 2 workers``: ``LocalCluster(2 processes x 1 thread)``; its start-up is timed
  apart. Every run is checked to give the same ``sweep.json`` numbers.

Scaling efficiency = T(in-process, 1 thread) / (2 x T(cluster)). Run from the repository root:

    .venv/bin/python benchmarks/bench_sweep.py
    .venv/bin/python benchmarks/bench_sweep.py --episodes 50    # a quicker, smaller sweep

Timings are never asserted anywhere.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from factorq_trainers.commands.paper import command as paper  # noqa: E402
from factorq_trainers.distributed import sweep, sweep_spec  # noqa: E402
from factorq_trainers.runner import cluster  # noqa: E402


def _spec(out: Path, episodes: int, threads: int) -> sweep_spec.SweepSpec:
    return sweep_spec.SweepSpec(
        base=(("episodes", episodes), ("threads", threads)),
        grid=(("obstacles", (5, 10, 15, 20)), ("eta", (0.05, 0.1, 0.2, 0.4))),
        seeds=100,
        out=str(out),
    )


def _numbers(result: dict) -> list:
    return [{**row, "config": None} for row in result["configurations"]]


def _timed_sweep(spec: sweep_spec.SweepSpec, executor) -> tuple[float, dict]:
    started = time.perf_counter()
    result = sweep.run_sweep(spec, executor)
    return time.perf_counter() - started, result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=200, help="episodes per run (200)")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="bench_sweep-"))
    print(f"16 configurations x 100 seeds, {args.episodes} episodes per run; "
          f"{os.cpu_count()} CPUs; scratch {root}", flush=True)  # fmt: skip
    paper.run(paper.PaperConfig(seeds=1, runs=1, episodes=1, out="unused"))  # build the kernel

    one, reference = _timed_sweep(_spec(root / "one", args.episodes, 1), cluster.InProcess())
    print(f"in-process, 1 thread: {one:.1f} s", flush=True)
    two, result = _timed_sweep(_spec(root / "two", args.episodes, 2), cluster.InProcess())
    assert _numbers(result) == _numbers(reference)
    print(f"in-process, 2 threads: {two:.1f} s", flush=True)

    import distributed

    started = time.perf_counter()
    local = distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=50
    )
    client = distributed.Client(local, set_as_default=False)
    client.wait_for_workers(2)
    executor = cluster.DaskExecutor(client)
    startup = time.perf_counter() - started
    print(f"cluster start-up: {startup:.1f} s", flush=True)
    on_cluster, result = _timed_sweep(_spec(root / "cluster", args.episodes, 1), executor)
    assert _numbers(result) == _numbers(reference)
    print(f"local cluster, 2 workers: {on_cluster:.1f} s", flush=True)
    executor.close()
    local.close()

    gather = result["timing"]["wall_s"] - result["timing"]["compute_s"]
    rows = [
        ("in-process, 1 thread", one, 1.0),
        ("in-process, 2 threads", two, one / two),
        ("local cluster, 2 workers x 1 thread", on_cluster, one / on_cluster),
    ]
    print("\n| where | wall s | speed-up vs 1 thread |\n| --- | ---: | ---: |")
    for name, seconds, speedup in rows:
        print(f"| {name} | {seconds:.1f} | {speedup:.2f}x |")
    print(
        f"\nscaling efficiency (2 workers): {one / (2 * on_cluster):.0%}; cluster start-up "
        f"{startup:.1f} s (not in the sweep's time); gathering 16 configurations (read back, "
        f"checked): {gather:.1f} s"
    )


if __name__ == "__main__":
    main()
