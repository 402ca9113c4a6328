"""Resource estimates before work: a run that would not fit is refused with the estimate and the
limit in one line (exit 2), before anything is allocated or written; a large one that fits
prints its estimate first."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import re

import pytest

from factorq_trainers import cli
from factorq_trainers.commands.compare.config import CompareConfig
from factorq_trainers.commands.paper.config import PaperConfig
from factorq_trainers.runner import resources

NEEDS = r"needs about [\d.]+ [KMGTP]iB of memory \(.+\) but [\d.]+ [KMGTP]?i?B is available"
PAPER_HINT = r"use fewer --seeds, --shard-seeds, --runs or --episodes, or a smaller --size"
COMPARE_HINT = r"use fewer --seeds or --steps, or a smaller --size"

#: Command, the part of the estimate that must dominate, the hint.
REFUSED = [
    ("paper --seeds 10000000", r"curves [\d.]+ TiB", PAPER_HINT),  # every seed's, gathered
    ("paper --episodes 100000000", r"metrics [\d.]+ TiB, curves", PAPER_HINT),
    ("paper --runs 2000000000", r"metrics [\d.]+ PiB", PAPER_HINT),
    # a unit of 1,000 seeds (in every regime) holds 3,000 experiments' tables at once
    (
        "paper --size 1000 --methods factor-q --seeds 1000 --shard-seeds 1000",
        r"tables [\d.]+ GiB",
        PAPER_HINT,
    ),
    (
        "paper --size 1000 --methods factor-q --seeds 1000 --shard-seeds 1000 --backend modular",
        r"tables [\d.]+ GiB",
        PAPER_HINT,
    ),
    ("compare --seeds 10000000", r"episode records [\d.]+ TiB", COMPARE_HINT),
    ("compare --steps 2000000000", r"episode records [\d.]+ TiB", COMPARE_HINT),
    ("compare --size 1000 --seeds 1000 --methods factor-q", r"tables [\d.]+ GiB", COMPARE_HINT),
    (
        "dependencies --seeds 100000000",
        r"learners, tables and metrics [\d.]+ TiB",
        r"use fewer --seeds, --runs or --episodes, or fewer --settings",
    ),
]
if importlib.util.find_spec("minigrid") is not None:  # the extra: its refusal comes first without
    REFUSED.append(
        (
            "minigrid --seeds 10000 --sizes 16 --steps 100000000",
            r"episode records [\d.]+ TiB",
            r"use fewer --seeds or --steps, or smaller --sizes",
        )
    )


def run_cli(command: str, tmp_path) -> tuple[int, str]:
    err = io.StringIO()
    args = [*command.split(), "--out", str(tmp_path / "out")]
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(args)
    return code, err.getvalue()


@pytest.mark.parametrize(("command", "part", "hint"), REFUSED, ids=[row[0] for row in REFUSED])
def test_a_run_that_does_not_fit_is_refused_before_any_work(
    command, part, hint, tmp_path, monkeypatch
):
    monkeypatch.setenv(resources.LIMIT_VARIABLE, str(16 * 2**30))
    code, err = run_cli(command, tmp_path)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    name = command.split()[0]
    assert lines[0].startswith(f"factorq {name}: error: this ")
    assert f"16.0 GiB is available ({resources.LIMIT_VARIABLE})" in lines[0]
    assert re.search(NEEDS, lines[0]) and re.search(part, lines[0])
    assert re.search(hint, lines[0])
    assert not (tmp_path / "out").exists()  # nothing started, nothing written


def test_a_large_run_that_fits_prints_its_estimate_first(tmp_path, monkeypatch):
    # The estimate of a tiny run is some kB: a limit of 3x makes it "large" (over a quarter).
    config = PaperConfig(seeds=1, runs=1, episodes=2, size=4, obstacles=1)
    from factorq_trainers.commands.paper import command as paper

    estimate = paper.estimate(config)
    monkeypatch.setenv(resources.LIMIT_VARIABLE, str(3 * estimate.bytes))
    code, err = run_cli("paper --seeds 1 --runs 1 --episodes 2 --size 4 --obstacles 1", tmp_path)
    assert code == 0, err
    line = err.splitlines()[0]
    assert line.startswith("this experiment needs about ") and "available, and at least " in line
    assert (tmp_path / "out" / "results.json").is_file()


def test_the_library_entry_points_check_too(tmp_path, monkeypatch):
    monkeypatch.setenv(resources.LIMIT_VARIABLE, "1000")
    from factorq_trainers.commands.compare import command as compare
    from factorq_trainers.commands.paper import command as paper

    with pytest.raises(resources.ResourceError, match=r"this experiment needs about .* 1000 B is"):
        paper.run(PaperConfig(seeds=1, runs=1, episodes=1, size=4, obstacles=1, out=str(tmp_path)))
    with pytest.raises(resources.ResourceError, match=r"this experiment needs about"):
        compare.run(CompareConfig(seeds=1, steps=1, size=4, obstacles=1, out=str(tmp_path)))
    from factorq_trainers.commands.dependencies import command as dependencies

    with pytest.raises(resources.ResourceError, match=r"this experiment needs about"):
        dependencies.run(dependencies.DependenciesConfig(seeds=1, settings=("cross",)))


def test_the_dependencies_estimate_grows_with_the_candidate_sets():
    from factorq_trainers.commands.dependencies import command as dependencies
    from factorq_trainers.commands.dependencies.config import DependenciesConfig

    cross = dependencies.estimate(DependenciesConfig(seeds=10, settings=("cross",)))
    ring = dependencies.estimate(DependenciesConfig(seeds=10, settings=("ring-24",)))
    # cross: 4 sensors, 11 candidate sets, ring-24: 32 sensors, 529 (of at most 2 parents each)
    learners = 2 * 8 * 8 * 4 * 4 * 10
    assert ring.bytes - cross.bytes >= learners * (529 - 11) - 10 * 4 * (1 << 4) * 12


def test_the_paper_estimate_is_close_to_what_the_default_run_allocates():
    # Measured peak RSS over the interpreter's baseline (`factorq paper --seeds 1 --runs 1
    # --episodes 1`): 90 MiB for the default config (100 seeds: two units) and 292 MiB for
    # --seeds 1000 (twenty units); the estimate must stay within 25% of both.
    from factorq_trainers.commands.paper import command as paper

    assert 68 < paper.estimate(PaperConfig()).bytes / 2**20 < 112
    assert 219 < paper.estimate(PaperConfig(seeds=1000)).bytes / 2**20 < 365


@pytest.mark.parametrize("value", ["-1", "lots", "1e9"])
def test_a_malformed_memory_limit_is_one_line(value, monkeypatch):
    monkeypatch.setenv(resources.LIMIT_VARIABLE, value)
    with pytest.raises(resources.ResourceError, match=r"FACTORQ_MEMORY_LIMIT=.* must be a number"):
        resources.available_memory()


def test_the_least_limit_wins(monkeypatch):
    monkeypatch.setenv(resources.LIMIT_VARIABLE, "12345")
    assert resources.available_memory() == (12345, resources.LIMIT_VARIABLE)


def test_a_sweep_that_does_not_fit_is_refused_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setenv(resources.LIMIT_VARIABLE, str(16 * 2**30))
    out = tmp_path / "sweep"
    code, err = run_cli(f"sweep --grid eta=0.1,0.2 --seeds 10000000 --out {out}", tmp_path)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert re.search(r"factorq sweep: error: this sweep needs about .* TiB .* but 16.0 GiB", err)
    assert not out.exists()


def test_a_sweep_of_whole_runs_counts_its_workers_and_every_runs_env_steps():
    tasks = [
        resources.Estimate({"tables": 10, "records": 5}, 100, exact_steps=True),
        resources.Estimate({"tables": 30, "records": 1}, 7, exact_steps=True),
        resources.Estimate({"tables": 1}, 1, exact_steps=False),
    ]
    alone = resources.tasks_estimate(tasks, workers=1)  # in-process: one at a time
    assert alone.parts == {"tables": 30, "records": 1} and alone.env_steps == 108
    assert not alone.exact_steps
    two = resources.tasks_estimate(tasks, workers=2)  # the largest, twice: hand-computed
    assert two.parts == {"tables x 2 at once": 60, "records x 2 at once": 2} and two.bytes == 62
    assert resources.tasks_estimate(tasks, workers=8).bytes == 31 * 3  # no more than 3 tasks


def test_a_compare_sweep_too_large_for_its_workers_is_refused_before_the_cluster_starts(
    tmp_path, monkeypatch
):
    config = CompareConfig(seeds=2000, steps=20000)
    from factorq_trainers.commands.compare import command as compare

    one = compare.estimate(config).bytes
    monkeypatch.setenv(resources.LIMIT_VARIABLE, str(int(one * 1.5)))  # one fits, two do not
    command = "sweep --command compare --seeds 2000 --set steps=20000 --grid seed=0,1"
    code, err = run_cli(f"{command} --cluster local:2", tmp_path)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert re.search(r"this sweep needs about .* \(episode records x 2 at once [\d.]+ GiB", err)
    assert lines[0].endswith("or fewer --cluster workers")
    assert not (tmp_path / "out").exists()
