"""The structure learner's options compared over several master seeds (issue 12).

Each ``--variant NAME:FIELD=VALUE,...`` is a ``DependenciesConfig`` with those fields changed
(``NAME:`` alone: the defaults). Every variant runs the learned structure and the oracle on every
setting for each ``--master-seeds`` seed (100 experiments each by default, on the compiled path),
and one row per variant prints, per setting, the fraction right within the target and the
collisions against the oracle, averaged over the seeds. ``docs/decisions.md``'s tables of Beta
priors and reopening thresholds were made this way, e.g.:

    .venv/bin/python benchmarks/bench_structure_options.py --variant defaults: \\
        --variant reopen:reopen_factor=10000 \\
        --variant old:prior_a=1,prior_b=1,bayes_factor=100,candidate_prior=size,reopen_factor=10000

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics

from factorq_trainers.experiments.dependencies import DependenciesConfig, run


def variant(text: str) -> tuple[str, dict[str, object]]:
    """``NAME:FIELD=VALUE,...`` -> (name, fields), each value read as the field's type."""
    name, _, assignments = text.partition(":")
    types = {field.name: field.type for field in dataclasses.fields(DependenciesConfig)}
    fields: dict[str, object] = {}
    for assignment in filter(None, assignments.split(",")):
        field, _, value = assignment.partition("=")
        if field not in types:
            raise SystemExit(f"--variant {text!r}: DependenciesConfig has no field {field!r}")
        fields[field] = value if "str" in str(types[field]) else float(value)
    for field in ("window", "max_parents", "change_run"):
        if field in fields:
            fields[field] = int(fields[field])
    return name, fields


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variant", action="append", type=variant, required=True)
    parser.add_argument("--master-seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--seeds", type=int, default=100)
    args = parser.parse_args()
    for name, fields in args.variant:
        rows: dict[str, tuple[list[float], list[float]]] = {}
        for seed in args.master_seeds:
            config = DependenciesConfig(
                seed=seed, seeds=args.seeds, methods=("learned", "oracle"), out="unused", **fields
            )
            for setting, summary in run(config)["settings"].items():
                right, ratio = rows.setdefault(setting, ([], []))
                right.append(summary["structure"]["fraction_right_within_target"])
                ratio.append(summary["against_oracle"]["collisions"]["ratio"])
        cells = [
            f"{setting} {100 * statistics.mean(right):.0f}%, {statistics.mean(ratio):.2f}x"
            for setting, (right, ratio) in rows.items()
        ]
        print(f"{name}: " + " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
