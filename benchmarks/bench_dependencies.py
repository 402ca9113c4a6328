"""Speed of the structure learner (issue 12): the compiled path against the modular one.

For each setting of ``factorq dependencies``, the wall time of ``run_learned_fast`` with
``--seeds`` experiments (default 100, the experiment's default) and of ``run_learned_modular``
with ``--modular-seeds`` (default 4: the torchrl path takes milliseconds per step), and the env
steps per second of each. Both give the same numbers bit for bit (tests/test_fast_structure.py).
Run from the repository root:

    .venv/bin/python benchmarks/bench_dependencies.py
    .venv/bin/python benchmarks/bench_dependencies.py --settings cross ring-24 --modular-seeds 0

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import time

from factorq_trainers.commands.dependencies.config import SETTINGS, DependenciesConfig
from factorq_trainers.commands.dependencies.methods import run_learned_fast, run_learned_modular


def timed(run, config: DependenciesConfig, setting: str) -> tuple[float, int]:
    started = time.perf_counter()
    result = run(config, setting)
    return time.perf_counter() - started, int(result["metrics"]["steps"].sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=list(SETTINGS))
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--modular-seeds", type=int, default=4)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    print("| setting | path | seeds | seconds | env steps / s |")
    print("| --- | --- | ---: | ---: | ---: |")
    for setting in args.settings:
        runs = [("fast", run_learned_fast, args.seeds)]
        if args.modular_seeds > 0:
            runs.append(("modular", run_learned_modular, args.modular_seeds))
        for path, run, seeds in runs:
            config = DependenciesConfig(seeds=seeds, threads=args.threads, out="unused")
            seconds, steps = timed(run, config, setting)
            print(f"| {setting} | {path} | {seeds} | {seconds:.2f} | {steps / seconds:,.0f} |")


if __name__ == "__main__":
    main()
