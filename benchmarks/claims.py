"""The headline ratios of the README and ``docs/results.md``, over master seeds (issue 39).

Each claim is a small record (``Claim``): its name, the run it reads (``RUNS``: the ``factorq``
command that produces it) and a function that reads the run's JSON into the ratio and the
absolute measures of both sides. For every selected claim the script runs its command once per
master seed (``sys.executable -m factorq_trainers.cli``, one run at a time, with disjoint seed
sets: ``--seed k`` where it is a master seed, ``--seed k * seeds`` where it is the first seed,
as in ``factorq risk``), then prints one Markdown table: the claim, the command, the median
ratio and its range [min, max] over the master seeds, in how many master seeds the claim's own
bar holds (where it has one), and the absolute measures beside it (median over the master seeds
of each side), so that a failure shared by both sides shows. A ratio of 0 / 0 reads "too little
data".

    .venv/bin/python benchmarks/claims.py                       # every cheap claim, 5 master seeds
    .venv/bin/python benchmarks/claims.py --only paper-c5,heading-greedy --master-seeds 5
    .venv/bin/python benchmarks/claims.py --only highway-gym-dqn   # minutes per run: ask for it

The runs' folders go to ``--out`` (default: a temporary folder), one per run and master seed
(``OUT/RUN/seedK``); a folder that already holds its run's JSON is read again, not rerun, so an
interrupted measurement continues where it stopped. Claims marked ``expensive`` (highway-env:
tens of minutes per run on 2 cores) run only when ``--only`` names them or ``--all`` is given.

Not a package on purpose (the torchrl wheel installs a top-level ``benchmarks``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

#: A reading: the ratio (``None``: 0 / 0) and the absolute measures, name -> value.
Reading = tuple[float | None, dict[str, float | None]]


@dataclass(frozen=True)
class Run:
    """A command that produces claims: its argv (after ``factorq``) for a master seed."""

    name: str
    argv: Callable[[int], list[str]]
    json: str
    expensive: bool = False


@dataclass(frozen=True)
class Claim:
    """A headline ratio: what the docs state, the runs it reads and how."""

    name: str
    runs: tuple[str, ...]
    stated: str
    read: Callable[..., Reading]
    holds: Callable[[float], bool] | None = None


WORLDS = ("static", "semi-dynamic", "dynamic")
MINIGRID_SIZES = ("5", "6", "8", "16")


def ratio(numerator: float | None, denominator: float | None) -> float | None:
    """``numerator / denominator``; ``None`` for 0 / 0 or a missing side, inf for x / 0."""
    if numerator is None or denominator is None:
        return None
    if denominator == 0:
        return None if numerator == 0 else float("inf")
    return numerator / denominator


# --------------------------------------------------------------------------------------------
# The runs


RUNS = {
    run.name: run
    for run in (
        Run("paper", lambda k: ["paper", "--seed", str(k)], "results.json"),
        Run("heading", lambda k: ["paper", "--body", "heading", "--seed", str(k)], "results.json"),
        Run(
            "ring",
            lambda k: [
                "paper",
                "--sensors",
                "ring",
                "--distractors",
                "4",
                "--sensor-permutation",
                "0",
                "--seed",
                str(k),
            ],
            "results.json",
        ),
        # DQN's numbers do not depend on the other methods (docs/tutorials/minigrid.md), so the
        # claim's two methods run alone.
        Run(
            "minigrid",
            lambda k: ["minigrid", "--methods", "factor-dqn-learned,dqn", "--seed", str(k)],
            "minigrid.json",
        ),
        # A method's numbers do not depend on the others (trainers/commands/compare/command.py).
        Run(
            "compare",
            lambda k: ["compare", "--methods", "dqn,factor-dqn", "--seed", str(k)],
            "comparison.json",
        ),
        # --seed is the first seed: 3 seeds per master seed.
        Run(
            "risk",
            lambda k: ["risk", "--methods", "dqn,dqn+risk", "--seed", str(3 * k)],
            "risk.json",
        ),
        Run(
            "highway-gym",
            lambda k: [
                "gym",
                "--world",
                "highway",
                "--methods",
                "dqn,factor-dqn,factor-dqn-learned,sb3-dqn",
                "--seed",
                str(k),
            ],
            "gym.json",
            expensive=True,
        ),
        Run(
            "highway-gym-20k",
            lambda k: [
                "gym",
                "--world",
                "highway",
                "--methods",
                "dqn,factor-dqn",
                "--seeds",
                "5",
                "--steps",
                "20000",
                "--eval-episodes",
                "10",
                "--seed",
                str(k),
            ],
            "gym.json",
            expensive=True,
        ),
        Run("transfer", lambda k: ["transfer", "--seed", str(k)], "transfer.json"),
        Run(
            "highway-risk",
            lambda k: [
                "risk",
                "--worlds",
                "highway",
                "--steps",
                "1000",
                "--eval-episodes",
                "5",
                "--seed",
                str(3 * k),
            ],
            "risk.json",
            expensive=True,
        ),
    )
}


# --------------------------------------------------------------------------------------------
# The readers


def _paper_mean(results: dict[str, Any], world: str, algorithm: str, measure: str) -> float:
    return results["cells"][f"{world}/{algorithm}"]["summary"][measure]["mean"]


def paper_greedy(results: dict[str, Any]) -> Reading:
    """Q-learning / Factor-Q greedy collisions in the world where it is smallest (C5)."""
    sides = {
        world: (
            _paper_mean(results, world, "q-learning", "greedy_collisions"),
            _paper_mean(results, world, "factor-q", "greedy_collisions"),
        )
        for world in WORLDS
    }
    ratios = {world: ratio(*pair) for world, pair in sides.items()}
    known = {world: value for world, value in ratios.items() if value is not None}
    if not known:
        return None, {}
    world = min(known, key=known.get)
    return known[world], {
        f"Q-learning greedy collisions ({world})": sides[world][0],
        f"Factor-Q greedy collisions ({world})": sides[world][1],
    }


def paper_claim(name: str, key: str | None = None) -> Callable[[dict[str, Any]], Reading]:
    """The value of ``factorq paper``'s claim ``name`` (``key``: one side of a dict value)."""

    def read(results: dict[str, Any]) -> Reading:
        value = results["claims"][name]["value"]
        if key is not None:
            value = value[key]
        return value, {}

    return read


def paper_static_collisions(results: dict[str, Any]) -> Reading:
    """Q-learning / Factor-Q collisions in the static world (C3)."""
    q = _paper_mean(results, "static", "q-learning", "collisions")
    f = _paper_mean(results, "static", "factor-q", "collisions")
    return ratio(q, f), {"Q-learning collisions": q, "Factor-Q collisions": f}


def paper_static_steps(results: dict[str, Any]) -> Reading:
    """Q-learning / Factor-Q total steps in the static world (C2)."""
    q = _paper_mean(results, "static", "q-learning", "total_steps")
    f = _paper_mean(results, "static", "factor-q", "total_steps")
    return ratio(q, f), {"Q-learning total steps": q, "Factor-Q total steps": f}


def paper_worst(results: dict[str, Any]) -> Reading:
    """The largest Factor-Q / Q-learning ratio of the 9 comparisons (C1: <= 1)."""
    return results["claims"]["C1"]["value"], {}


def heading_factor_q_greedy(results: dict[str, Any]) -> Reading:
    """The smallest Q-learning / Factor-Q greedy collisions of the three worlds, both sides'
    largest and smallest greedy collisions beside it."""
    value, _ = paper_greedy(results)
    q = [_paper_mean(results, w, "q-learning", "greedy_collisions") for w in WORLDS]
    f = [_paper_mean(results, w, "factor-q", "greedy_collisions") for w in WORLDS]
    return value, {
        "Q-learning greedy collisions (min)": min(q),
        "Q-learning greedy collisions (max)": max(q),
        "Factor-Q greedy collisions (max)": max(f),
    }


def _summed(results: dict[str, Any], algorithm: str, measure: str) -> float:
    return sum(_paper_mean(results, w, algorithm, measure) for w in WORLDS)


def ring_against_paper(measure: str, algorithm: str) -> Callable[..., Reading]:
    """``algorithm``'s ``measure`` (summed over the worlds), ring body / the paper's body."""

    def read(ring: dict[str, Any], paper: dict[str, Any]) -> Reading:
        r, p = _summed(ring, algorithm, measure), _summed(paper, algorithm, measure)
        return ratio(r, p), {f"{algorithm} {measure}, ring": r, f"{algorithm} {measure}, paper": p}

    return read


def _minigrid(results: dict[str, Any], size: str, method: str, measure: str) -> float | None:
    return results["results"][size][method]["summary"][measure]["mean"]


def minigrid_collisions(size: str) -> Callable[[dict[str, Any]], Reading]:
    """DQN / learned Factor-Q training collisions at ``size``, success rates beside them."""

    def read(results: dict[str, Any]) -> Reading:
        dqn = _minigrid(results, size, "dqn", "collisions")
        learned = _minigrid(results, size, "factor-dqn-learned", "collisions")
        return ratio(dqn, learned), {
            "DQN collisions": dqn,
            "learned collisions": learned,
            "DQN success": _minigrid(results, size, "dqn", "success_rate"),
            "learned success": _minigrid(results, size, "factor-dqn-learned", "success_rate"),
        }

    return read


def minigrid_found(results: dict[str, Any]) -> Reading:
    """The share of seeds, over all sizes, in which the learner found forward <- front, and the
    smallest and largest of the sizes' mean steps it took (a share, not a ratio)."""
    found = [results["results"][s]["factor-dqn-learned"]["summary"] for s in MINIGRID_SIZES]
    steps = [entry["found_forward_front"]["mean"] for entry in found]
    known = [s for s in steps if s is not None]
    return statistics.mean(entry["found_at_all"] for entry in found), {
        "steps to find (min of sizes)": min(known, default=None),
        "steps to find (max of sizes)": max(known, default=None),
    }


def compare_ratio(world: str, measure: str) -> Callable[[dict[str, Any]], Reading]:
    """DQN / neural Factor-Q ``measure`` in ``world`` (``factorq compare``)."""

    def read(results: dict[str, Any]) -> Reading:
        dqn = results["results"]["dqn"][world][measure]
        neural = results["results"]["factor-dqn"][world][measure]
        return ratio(dqn, neural), {f"DQN {measure}": dqn, f"neural Factor-Q {measure}": neural}

    return read


def _risk_row(results: dict[str, Any], world: str, method: str) -> dict[str, Any]:
    return next(r for r in results["rows"] if r["world"] == world and r["method"] == method)


def risk_ratio(world: str, base: str, other: str) -> Callable[[dict[str, Any]], Reading]:
    """``base`` / ``other`` training collisions in ``world`` (``factorq risk``)."""

    def read(results: dict[str, Any]) -> Reading:
        a, b = _risk_row(results, world, base), _risk_row(results, world, other)
        return ratio(a["train_collisions"], b["train_collisions"]), {
            f"{base} collisions": a["train_collisions"],
            f"{other} collisions": b["train_collisions"],
            f"{base} final return": a["final_return"],
            f"{other} final return": b["final_return"],
            f"{base} greedy success": a["greedy_success"],
            f"{other} greedy success": b["greedy_success"],
        }

    return read


def transfer_ratio(regime: str) -> Callable[[dict[str, Any]], Reading]:
    """Factor-Q from scratch / with the carried body model: collisions in the target's first
    episodes (``factorq transfer``), the final steps per episode beside them."""

    def read(results: dict[str, Any]) -> Reading:
        methods = results["results"][regime]
        fresh, body = methods["factor-q"], methods["factor-q-body"]
        return ratio(fresh["early_collisions"]["mean"], body["early_collisions"]["mean"]), {
            "fresh early collisions": fresh["early_collisions"]["mean"],
            "carried early collisions": body["early_collisions"]["mean"],
            "fresh final steps": fresh["late_steps"]["mean"],
            "carried final steps": body["late_steps"]["mean"],
        }

    return read


def gym_ratio(base: str, other: str) -> Callable[[dict[str, Any]], Reading]:
    """``base`` / ``other`` training crashes per 1,000 steps (``factorq gym``)."""

    def read(results: dict[str, Any]) -> Reading:
        methods = results["methods"]
        a = methods[base]["crashes_per_1000"]["mean"]
        b = methods[other]["crashes_per_1000"]["mean"]
        return ratio(a, b), {
            f"{base} crashes/1000": a,
            f"{other} crashes/1000": b,
            f"{base} greedy return": methods[base]["greedy_return"]["mean"],
            f"{other} greedy return": methods[other]["greedy_return"]["mean"],
        }

    return read


def gym_phases(base: str, other: str, phase: int) -> Callable[[dict[str, Any]], Reading]:
    """``gym_ratio``, plus each side's training crashes per 1,000 steps over the first and the
    last ``phase`` env steps (the mean over the seeds' crash curves): where the gain is."""
    whole = gym_ratio(base, other)

    def read(results: dict[str, Any]) -> Reading:
        value, measures = whole(results)
        for method in (base, other):
            curves = results["methods"][method]["curves"]
            steps = curves["curve_steps"][0]
            start, end = steps.index(phase), steps.index(steps[-1] - phase)
            seeds = curves["curve_crashes"]
            first = statistics.fmean(seed[start] for seed in seeds)
            last = statistics.fmean(seed[-1] - seed[end] for seed in seeds)
            measures[f"{method} crashes/1000, first {phase}"] = 1000 * first / phase
            measures[f"{method} crashes/1000, last {phase}"] = 1000 * last / phase
        return value, measures

    return read


# --------------------------------------------------------------------------------------------
# The claims


def _above(bar: float) -> Callable[[float], bool]:
    return lambda value: value > bar


def _at_least(bar: float) -> Callable[[float], bool]:
    return lambda value: value >= bar


CLAIMS = [
    *(
        Claim(
            f"transfer-{regime}",
            ("transfer",),
            f"transfer {regime}: a carried body model, fewer early collisions (target 5x)",
            transfer_ratio(regime),
            _at_least(5),
        )
        for regime in ("static", "semi-dynamic", "dynamic")
    ),
    Claim(
        "paper-c1",
        ("paper",),
        "C1: Factor-Q / Q-learning <= 1 everywhere",
        paper_worst,
        lambda v: v <= 1,
    ),
    Claim(
        "paper-c2",
        ("paper",),
        "C2: static steps Q-learning / Factor-Q 1.08, in [0.8, 1.25]",
        paper_static_steps,
        lambda v: 0.8 <= v <= 1.25,
    ),
    Claim(
        "paper-c3",
        ("paper",),
        "C3: static collisions 49.5x, > 10",
        paper_static_collisions,
        _above(10),
    ),
    Claim(
        "paper-c4-factor-q",
        ("paper",),
        "C4: Factor-Q moving/static speed 0.853, >= 0.85",
        paper_claim("C4", "factor-q"),
        _at_least(0.85),
    ),
    Claim(
        "paper-c4-q-learning",
        ("paper",),
        "C4: Q-learning worst 0.530, in [0.45, 0.70]",
        paper_claim("C4", "q-learning"),
        lambda v: 0.45 <= v <= 0.70,
    ),
    Claim(
        "paper-c5",
        ("paper",),
        "C5: greedy collisions 128x fewer, > 100 in every world",
        paper_greedy,
        _above(100),
    ),
    Claim(
        "heading-greedy",
        ("heading",),
        "heading: 0.1 greedy collisions against 895-2451",
        heading_factor_q_greedy,
        _above(100),
    ),
    Claim(
        "heading-c4",
        ("heading",),
        "heading: Factor-Q moving worlds almost as fast (C4)",
        paper_claim("C4", "factor-q"),
        _at_least(0.85),
    ),
    Claim(
        "ring-factor-q-same",
        ("ring", "paper"),
        "ring: Factor-Q identical to the paper body",
        ring_against_paper("total_steps", "factor-q"),
        lambda v: v == 1,
    ),
    Claim(
        "ring-q-learning-steps",
        ("ring", "paper"),
        "ring: Q-learning about 4x slower",
        ring_against_paper("total_steps", "q-learning"),
    ),
    Claim(
        "ring-q-learning-collisions",
        ("ring", "paper"),
        "ring: Q-learning 4-5x the collisions",
        ring_against_paper("collisions", "q-learning"),
    ),
    *(
        Claim(
            f"minigrid-{size}",
            ("minigrid",),
            f"MiniGrid {size}x{size}: 11.5-14.4x fewer training collisions than DQN (>= 10x)",
            minigrid_collisions(size),
            _at_least(10),
        )
        for size in MINIGRID_SIZES
    ),
    Claim(
        "minigrid-found",
        ("minigrid",),
        "MiniGrid: forward <- front in 10/10 seeds (share)",
        minigrid_found,
        lambda v: v == 1,
    ),
    *(
        Claim(
            f"compare-sooner-{world}",
            ("compare",),
            f"compare {world}: about 6x sooner",
            compare_ratio(world, "steps_to_threshold"),
        )
        for world in WORLDS
    ),
    *(
        Claim(
            f"compare-collisions-{world}",
            ("compare",),
            f"compare {world}: 5x less",
            compare_ratio(world, "collisions"),
        )
        for world in WORLDS
    ),
    Claim(
        "risk-grid",
        ("risk",),
        "risk grid: 14.3x fewer training collisions",
        risk_ratio("grid", "dqn", "dqn+risk"),
    ),
    Claim(
        "risk-minigrid",
        ("risk",),
        "risk MiniGrid: 70.3x fewer training collisions",
        risk_ratio("minigrid", "dqn", "dqn+risk"),
    ),
    Claim(
        "highway-gym-dqn",
        ("highway-gym",),
        "highway: 1.28x fewer crashes than DQN (target 5x)",
        gym_ratio("dqn", "factor-dqn"),
        _at_least(5),
    ),
    Claim(
        "highway-gym-sb3",
        ("highway-gym",),
        "highway: 2.13x fewer crashes than SB3 (target 5x)",
        gym_ratio("sb3-dqn", "factor-dqn"),
        _at_least(5),
    ),
    Claim(
        "highway-gym-learned",
        ("highway-gym",),
        "highway: learned 1.25x the oracle's (1.5x)",
        gym_ratio("factor-dqn-learned", "factor-dqn"),
        lambda v: v <= 1.5,
    ),
    Claim(
        "highway-20k-dqn",
        ("highway-gym-20k",),
        "highway at 20,000 steps: fewer crashes than DQN (target 3x)",
        gym_phases("dqn", "factor-dqn", 5000),
        _at_least(3),
    ),
    Claim(
        "highway-risk-oracle",
        ("highway-risk",),
        "risk highway: 1.04x fewer (target 5x)",
        risk_ratio("highway", "dqn", "dqn+risk"),
        _at_least(5),
    ),
    Claim(
        "highway-risk-learned",
        ("highway-risk",),
        "risk highway: learned 0.94x the oracle's (1.5x)",
        risk_ratio("highway", "dqn+risk-learned", "dqn+risk"),
        lambda v: v <= 1.5,
    ),
]


# --------------------------------------------------------------------------------------------
# Running and the table


def run_once(run: Run, master: int, out: Path, extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """``run``'s JSON for master seed ``master``: read from its folder, or made there first
    (with ``extra`` arguments, e.g. ``--cluster off``: they change where units run, not what
    they compute)."""
    folder = out / run.name / f"seed{master}"
    path = folder / run.json
    argv = [*run.argv(master), *extra, "--out", str(folder)]
    if path.exists():
        print(f"{run.name} master seed {master}: kept ({path})", flush=True)
    else:
        start = time.monotonic()
        log = out / run.name / f"seed{master}.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        with log.open("w") as handle:
            done = subprocess.run(
                [sys.executable, "-m", "factorq_trainers.cli", *argv, "--force"],
                stdout=handle,
                stderr=subprocess.STDOUT,
                check=False,
            )
        wall = time.monotonic() - start
        print(
            f"{run.name} master seed {master}: {wall:.0f} s wall (rc {done.returncode})", flush=True
        )
        if done.returncode != 0:
            raise SystemExit(f"factorq {' '.join(argv)} failed: see {log}")
    return json.loads(path.read_text())


def _number(value: float | None) -> str:
    if value is None:
        return "too little data"
    if value == float("inf"):
        return "inf"
    if abs(value) >= 100:
        return f"{value:,.0f}"
    if abs(value) >= 10:
        return f"{value:.1f}"
    return f"{value:.3g}"


def _median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return statistics.median(known) if known else None


def row(claim: Claim, readings: list[Reading]) -> str:
    """One Markdown row: the claim, its command, the median [min, max] and the measures."""
    ratios = [value for value, _ in readings]
    known = [v for v in ratios if v is not None]
    if known:
        spread = (
            f"{_number(statistics.median(known))} [{_number(min(known))}, {_number(max(known))}]"
        )
        if len(known) < len(ratios):
            spread += f" ({len(ratios) - len(known)} of {len(ratios)}: too little data)"
    else:
        spread = "too little data"
    holds = "-"
    if claim.holds is not None:
        holds = f"{sum(claim.holds(v) for v in known)}/{len(ratios)}"
    names = list(readings[0][1]) if readings else []
    measures = "; ".join(
        f"{name} {_number(_median([r[1].get(name) for r in readings]))}" for name in names
    )
    command = " + ".join(
        f"`factorq {' '.join(RUNS[name].argv(0)).replace(' --seed 0', '')}`" for name in claim.runs
    )
    cells = [f"`{claim.name}`: {claim.stated}", command, spread, holds, measures or "-"]
    return "| " + " | ".join(cells) + " |"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--master-seeds", type=int, default=5, help="master seeds 0 .. N-1")
    parser.add_argument("--only", default="", help="claims to measure, comma-separated names")
    parser.add_argument("--all", action="store_true", help="the expensive (highway) claims too")
    parser.add_argument("--out", type=Path, default=None, help="folder of the runs (default: temp)")
    parser.add_argument("--list", action="store_true", help="list the claims and stop")
    parser.add_argument(
        "--cluster", help="passed to every run (off: each run in one process, units one by one)"
    )
    args = parser.parse_args(argv)
    if args.list:
        for claim in CLAIMS:
            print(f"{claim.name}: {claim.stated}")
        return
    names = [name for name in args.only.split(",") if name]
    unknown = sorted(set(names) - {claim.name for claim in CLAIMS})
    if unknown:
        parser.error(f"unknown claims: {', '.join(unknown)} (--list lists them)")
    chosen = [
        claim
        for claim in CLAIMS
        if (claim.name in names)
        or (not names and (args.all or not any(RUNS[r].expensive for r in claim.runs)))
    ]
    out = args.out or Path(tempfile.mkdtemp(prefix="factorq-claims-"))
    print(f"runs in {out}", flush=True)
    masters = range(args.master_seeds)
    needed = list(dict.fromkeys(r for claim in chosen for r in claim.runs))
    extra = ("--cluster", args.cluster) if args.cluster else ()
    results = {(r, k): run_once(RUNS[r], k, out, extra) for r in needed for k in masters}
    print()
    print(f"Over {args.master_seeds} master seeds (median [min, max]; measures: medians):")
    print()
    print("| claim | command | ratio | holds | absolute measures |")
    print("| --- | --- | --- | --- | --- |")
    for claim in chosen:
        readings = [claim.read(*(results[r, k] for r in claim.runs)) for k in masters]
        print(row(claim, readings))


if __name__ == "__main__":
    main()
