"""``factorq paper`` on the runner's frame: its units (an algorithm x a shard of seeds) give the
numbers of one batch bit for bit, whatever the shards, the backend or the processes; a run killed
at any moment resumes from its kept units to the uninterrupted results; a kept unit of another
configuration, or edited and resealed, is refused before any work. The kernel refuses a state out
of its buffers' range whatever its source."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper.command import PaperConfig
from factorq_trainers.compiled import fast
from factorq_trainers.runner import kept
from factorq_trainers.runner.results import dumps as dumps_results

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
TINY = {"seeds": 5, "runs": 2, "episodes": 4, "size": 5, "obstacles": 3}
CLI_TINY = ["--seeds", "5", "--runs", "2", "--episodes", "4", "--size", "5", "--obstacles", "3"]


def _numbers(results: dict) -> str:
    """Everything of a results dict that must repeat: all but its timing and config."""
    return dumps_results({k: v for k, v in results.items() if k not in ("timing", "config")})


@pytest.fixture(scope="module")
def whole():
    if not fast.is_available():
        pytest.skip("fast backend unavailable")
    return paper.run(PaperConfig(**TINY))


def test_units_cover_every_algorithm_and_seed_once_in_shards():
    config = PaperConfig(**{**TINY, "first_seed": 3, "shard_seeds": 2})
    units = paper.units(config)
    assert [unit["id"] for unit in units] == [
        f"{algorithm}/{first}-{stop}"
        for algorithm in ("q-learning", "factor-q")
        for first, stop in ((3, 5), (5, 7), (7, 8))
    ]
    assert sum(paper.work(config, unit) for unit in units) == 2 * 3 * 5 * 2 * 4


@needs_fast
@pytest.mark.parametrize("shard_seeds", [1, 2, 5])
def test_shards_give_the_numbers_of_one_batch_bit_for_bit(whole, shard_seeds):
    sharded = paper.run(PaperConfig(**TINY, shard_seeds=shard_seeds))
    assert sharded["timing"]["units"] == 2 * -(-TINY["seeds"] // shard_seeds)
    assert _numbers(sharded) == _numbers(whole)


@needs_fast
def test_the_modular_path_in_shards_gives_the_fast_paths_numbers():
    short = {**TINY, "episodes": 2}  # 2 runs still: a run boundary on both paths
    modular = paper.run(PaperConfig(**short, backend="modular", shard_seeds=3))
    assert modular["timing"]["backend"] == "modular"
    assert _numbers(modular) == _numbers(paper.run(PaperConfig(**short)))


@needs_fast
def test_a_seed_range_alone_draws_what_it_draws_inside_the_whole_run(whole):
    part = paper.run(PaperConfig(**{**TINY, "first_seed": 2, "seeds": 3}))
    for name, cell in part["cells"].items():
        for measure, values in cell["per_seed"].items():
            assert values == whole["cells"][name]["per_seed"][measure][2:]


@needs_fast
def test_the_modular_path_runs_its_units_in_processes_with_the_same_numbers(tmp_path):
    pytest.importorskip("distributed")
    out = tmp_path / "modular"
    # 2 seeds: 4 units, two in each process (a process's second unit repeats too); 1 run of 2
    # episodes each (a unit's seconds are the processes' start-up, not its steps)
    small = {**TINY, "seeds": 2, "runs": 1, "episodes": 2}
    argv = ["paper", *(f"--{key}={value}" for key, value in small.items()), "--shard-seeds", "1"]
    code = cli.main([*argv, "--backend", "modular", "--threads", "2", "--out", str(out)])
    assert code == 0
    results = json.loads((out / "results.json").read_text())
    assert results["timing"]["where"].startswith("Dask")  # the runner's one pool
    assert _numbers(results) == _numbers(paper.run(PaperConfig(**small)))


# --------------------------------------------------------------------------------------------
# Resume from kept units


def _interrupted(tmp_path, monkeypatch, capsys, argv=()) -> Path:
    """A ``factorq paper`` run interrupted after its first unit (kept), exit 130."""
    out = tmp_path / "cut"
    real = paper.run_unit
    ran: list[str] = []

    def once(config, unit, *rest, **keywords):
        if ran:
            raise KeyboardInterrupt
        ran.append(unit["id"])
        return real(config, unit, *rest, **keywords)

    monkeypatch.setattr(paper, "run_unit", once)
    assert cli.main(["paper", *CLI_TINY, "--shard-seeds", "2", *argv, "--out", str(out)]) == 130
    assert "resume it with --resume" in capsys.readouterr().err
    monkeypatch.setattr(paper, "run_unit", real)
    return out


@needs_fast
def test_an_interrupted_run_resumes_to_the_uninterrupted_numbers(
    tmp_path, monkeypatch, capsys, whole
):
    out = _interrupted(tmp_path, monkeypatch, capsys)
    assert not (out / "results.json").exists()
    assert cli.main(["paper", "--resume", str(out), "--threads", "1"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["timing"]["units_resumed"] == 1
    assert _numbers(results) == _numbers(whole)
    assert not (out / "units").exists()  # nothing left to resume


@needs_fast
def test_resume_with_another_number_changing_option_names_it(tmp_path, monkeypatch, capsys):
    out = _interrupted(tmp_path, monkeypatch, capsys)
    assert cli.main(["paper", "--resume", str(out), "--epsilon", "0.2"]) == 2
    err = capsys.readouterr().err
    assert "epsilon=0.2 given, 0.01 kept" in err and err.count("\n") == 1


def _kept_unit(out: Path) -> Path:
    (path,) = [p for p in (out / "units").iterdir() if p.name != kept.RUN_FILE]
    return path


def _reseal(path: Path, edit) -> None:
    record = json.loads(path.read_text())
    record.pop(kept.DIGEST_KEY)
    edit(record)
    record[kept.DIGEST_KEY] = kept.json_digest(record)
    path.write_text(json.dumps(record))


@needs_fast
@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda r: r["result"]["worlds"][0]["run_sums"]["collisions"].__setitem__(0, -999),
         "negative"),
        (lambda r: r["result"]["worlds"][0]["task_return"].__setitem__(0, None), None),
        (lambda r: r["result"]["worlds"][0]["run_sums"]["collisions"].pop(), "seeds, not 2"),
        (lambda r: r["result"]["worlds"][1]["curve_sums"]["steps"][0].pop(),
         "episodes, not 4"),
        (lambda r: r["result"]["worlds"].reverse(), "holds the worlds"),
        (lambda r: r[kept.TIE_KEY].__setitem__("config_sha256", "0" * 64),
         "another configuration"),
    ],
)  # fmt: skip
def test_a_kept_unit_edited_and_resealed_is_refused_before_any_work(
    tmp_path, monkeypatch, capsys, edit, words
):
    out = _interrupted(tmp_path, monkeypatch, capsys)
    path = _kept_unit(out)
    _reseal(path, edit)
    before = path.read_bytes()
    ran: list[str] = []
    real = paper.run_unit
    monkeypatch.setattr(paper, "run_unit", lambda *a, **k: ran.append("unit") or real(*a, **k))
    assert cli.main(["paper", "--resume", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and "--force" in err and "Traceback" not in err, err
    if words is not None:
        assert words in err, err
    assert not ran and path.read_bytes() == before  # no work, nothing overwritten


@needs_fast
def test_a_kept_unit_of_another_configuration_is_refused(tmp_path, monkeypatch, capsys):
    first = _interrupted(tmp_path / "a", monkeypatch, capsys)
    other = _interrupted(tmp_path / "b", monkeypatch, capsys, ["--seed", "1"])
    copied = other / "units" / _kept_unit(first).name
    copied.write_bytes(_kept_unit(first).read_bytes())
    assert cli.main(["paper", "--resume", str(other)]) == 2
    assert "kept for another configuration" in capsys.readouterr().err


@needs_fast
def test_a_units_folder_that_is_a_link_is_refused(tmp_path, monkeypatch, capsys):
    out = _interrupted(tmp_path, monkeypatch, capsys)
    elsewhere = tmp_path / "elsewhere"
    (out / "units").rename(elsewhere)
    (out / "units").symlink_to(elsewhere, target_is_directory=True)
    assert cli.main(["paper", "--resume", str(out)]) == 2
    err = capsys.readouterr().err
    assert "units" in err and "Traceback" not in err, err


# --------------------------------------------------------------------------------------------
# Killed at any moment


def _start(cwd: Path, *argv: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "factorq_trainers.cli", "paper", *argv],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONHASHSEED": "0"},
    )


@needs_fast
def test_a_run_killed_mid_unit_and_resumed_writes_the_uninterrupted_results(tmp_path):
    # Long enough units (seeds x episodes) that the kill lands inside the work.
    argv = ["--seeds", "6", "--shard-seeds", "1", "--runs", "2", "--episodes", "60"]
    config = PaperConfig(seeds=6, runs=2, episodes=60, out="run")
    reference = paper.run(config)
    work = tmp_path / "killed"
    work.mkdir()
    out = work / "run"
    process = _start(work, *argv, "--out", "run")
    try:
        deadline = time.monotonic() + patience(120)
        while process.poll() is None and len(list((out / "units").glob("*.json"))) < 3:
            assert time.monotonic() < deadline, "no unit kept in time"
            time.sleep(0.005)
        if process.poll() is None:  # one unit kept (and run.json): kill it mid-way
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=patience(60))
            assert not (out / "results.json").exists()
            process = _start(work, "--resume", "run")
        _, err = process.communicate(timeout=patience(300))
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 0, err.decode()
    assert b"Traceback" not in err
    results = json.loads((out / "results.json").read_text())
    assert _numbers(results) == _numbers(reference)
    assert sorted(p.name for p in out.iterdir() if p.name != ".factorq.lock") == [
        "figure3.png",
        "report.md",
        "results.json",
    ]


# --------------------------------------------------------------------------------------------
# The kernel's own range checks


#: Fields of the kernel's state and a value out of its buffers' range, set behind
#: ``load_state_dict``'s back: the kernel itself refuses them (never an out-of-bounds access).
KERNEL_STATE = [
    ("cell", -100_000),
    ("cell", 10**12),
    ("run", -100_000),
    ("episode", 10**12),
    ("episode", -(10**9)),
    ("episode_step", -5),
    ("episode_step", 10**12),
    ("scatters", -1),
    ("policy_counter", -1),
    ("periods", -3),
    ("obstacle_pads", -7),
    ("obstacle_pads", 10**6),
    ("heading", 9),
    ("ticks", -1),
    ("kappa", -2),
    ("episode_collisions", -1),
]


@needs_fast
@pytest.mark.parametrize(
    ("field", "value"), KERNEL_STATE, ids=[f"{f}={v}" for f, v in KERNEL_STATE]
)
@pytest.mark.parametrize("threads", [1, 2])
def test_the_kernel_refuses_a_state_out_of_range_whatever_its_source(field, value, threads):
    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys

    batch = fast.ExperimentBatch(
        "factor-q",
        torch.tensor([0, 1, 1]),
        WorldConfig(size=5, num_obstacles=3),
        AgentConfig(),
        2,
        3,
        derive_keys(0, STREAM_WORLD, 3),
        derive_keys(0, STREAM_POLICY, 3),
        threads=threads,
    )
    batch.advance(7)
    batch._tensors[field][-1].view(-1)[-1] = value  # the last experiment's (or its last entry)
    with pytest.raises(ValueError, match=rf"the fast kernel refused experiment 2: its {field} is"):
        batch.advance(1_000)
