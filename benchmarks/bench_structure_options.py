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

Three more fields change the compiled path's mixture likelihood, which the config does not
carry (``functional.NOISY_ODDS`` and ``NOISY_PRIOR``, patched in ``batch_options`` for the
variant's runs): ``noisy_odds``, ``noisy_a``, ``noisy_b``. ``--per-seed`` prints each master
seed's share right, wrong commitments per 1,000 and collision ratio instead of the means. The
sweep of a body-level noisy prior in ``docs/decisions.md`` (issue 27) is

    .venv/bin/python benchmarks/bench_structure_options.py --per-seed \
        --settings noise-5,noise-10,ring-12-noise-5,ring-12-noise-10 --variant defaults: \
        --variant o100-b1:noisy_odds=100,noisy_a=1,noisy_b=1 \
        --variant o16-b2:noisy_odds=16

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics

from factorq_trainers.commands.dependencies.command import run
from factorq_trainers.commands.dependencies.config import DependenciesConfig
from factorq_trainers.compiled import batch_options

#: The mixture's constants a variant may change (not config fields: see the module docstring).
MIXTURE_FIELDS = ("noisy_odds", "noisy_a", "noisy_b")


def variant(text: str) -> tuple[str, dict[str, object]]:
    """``NAME:FIELD=VALUE,...`` -> (name, fields), each value read as the field's type."""
    name, _, assignments = text.partition(":")
    types = {field.name: field.type for field in dataclasses.fields(DependenciesConfig)}
    types |= {field: "float" for field in MIXTURE_FIELDS}
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
    parser.add_argument("--settings", default=None, help="Settings, comma-separated (all).")
    parser.add_argument("--per-seed", action="store_true", help="Every seed, not the means.")
    args = parser.parse_args()
    chosen = {} if args.settings is None else {"settings": tuple(args.settings.split(","))}
    defaults = batch_options.NOISY_ODDS, batch_options.NOISY_PRIOR
    for name, given in args.variant:
        fields = {key: value for key, value in given.items() if key not in MIXTURE_FIELDS}
        batch_options.NOISY_ODDS = float(given.get("noisy_odds", defaults[0]))  # type: ignore[arg-type]
        batch_options.NOISY_PRIOR = (
            float(given.get("noisy_a", defaults[1][0])),  # type: ignore[arg-type]
            float(given.get("noisy_b", defaults[1][1])),  # type: ignore[arg-type]
        )
        rows: dict[str, tuple[list[float], list[float], list[float]]] = {}
        for seed in args.master_seeds:
            config = DependenciesConfig(
                seed=seed,
                seeds=args.seeds,
                methods=("factor-q-learned", "factor-q"),
                out="unused",
                **chosen,
                **fields,
            )
            for setting, summary in run(config)["settings"].items():
                right, wrong, ratio = rows.setdefault(setting, ([], [], []))
                right.append(summary["structure"]["fraction_right_within_target"])
                wrong.append(summary["structure"]["wrong_commitments_per_1000"])
                ratio.append(summary["against_oracle"]["collisions"]["ratio"])
        batch_options.NOISY_ODDS, batch_options.NOISY_PRIOR = defaults
        if args.per_seed:
            cells = [
                f"{setting} {'/'.join(f'{100 * x:.0f}' for x in right)}%, "
                f"{'/'.join(f'{x:.0f}' for x in wrong)} wrong, "
                f"{'/'.join(f'{x:.2f}' for x in ratio)}x"
                for setting, (right, wrong, ratio) in rows.items()
            ]
        else:
            cells = [
                f"{setting} {100 * statistics.mean(right):.0f}%, {statistics.mean(ratio):.2f}x"
                for setting, (right, _, ratio) in rows.items()
            ]
        print(f"{name}: " + " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
