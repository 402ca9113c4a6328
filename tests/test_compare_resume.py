"""``factorq compare`` resumes per unit on the runner's frame (issue 37): a unit is a method's
batch, kept in ``OUT/units/`` as it finishes, so a comparison interrupted (Ctrl-C, SIGKILL) and
resumed with ``--resume OUT``, here or on a cluster, writes the numbers and logs of an
uninterrupted run; a kept unit of another config, or edited and sealed again with impossible
values, is refused in one line naming the file and ``--force``."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_kept_units import _reseal  # edit a kept file and seal it again, as anyone can
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.compare import command as compare
from factorq_trainers.methods.dqn import DQNConfig
from factorq_trainers.runner import kept

#: A comparison on the command line that runs in seconds: factor-q, then DQN (the one cut).
ARGS = ["--methods", "factor-q,dqn", "--seeds", "1", "--steps", "300", "--size", "4",
        "--obstacles", "1", "--regimes", "static,dynamic", "--threads", "1"]  # fmt: skip


def _cli_quiet(*argv: str) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(list(argv))
    return code, err.getvalue()


def _numbers(results: dict) -> dict:
    """``comparison.json`` without what measures time (or names the directory)."""
    results = json.loads(json.dumps(results))
    results.pop("timing")
    results["config"].pop("out")
    for method in results["results"].values():
        for world in method.values():
            world.pop("wall_s")
    return results


def _files(out: Path) -> dict[str, object]:
    """comparison.json's numbers and every log file, by path (the figure holds no number the
    json lacks)."""
    files: dict[str, object] = {
        "comparison.json": _numbers(json.loads((out / "comparison.json").read_text()))
    }
    for path in sorted((out / "logs").rglob("*")):
        if path.is_file():
            files[str(path.relative_to(out))] = path.read_bytes()
    return files


@pytest.fixture(scope="module")
def whole(tmp_path_factory) -> Path:
    """An uninterrupted run of ``ARGS``: its out directory."""
    out = tmp_path_factory.mktemp("compare") / "whole"
    code, err = _cli_quiet("compare", *ARGS, "--out", str(out))
    assert code == 0, err
    return out


def _cut(out: Path, monkeypatch, *extra: str) -> Path:
    """A run of ``ARGS`` (and ``extra``) interrupted (Ctrl-C) when DQN starts: factor-q kept."""
    run_unit = compare.run_unit

    def interrupted(config, unit, *rest, **keywords):
        if unit["method"] == "dqn":
            raise KeyboardInterrupt
        return run_unit(config, unit, *rest, **keywords)

    monkeypatch.setattr(compare, "run_unit", interrupted)
    code, err = _cli_quiet("compare", *ARGS, *extra, "--out", str(out))
    monkeypatch.setattr(compare, "run_unit", run_unit)
    assert code == cli.EXIT_INTERRUPTED and f"resume it with --resume {out}" in err, err
    assert kept.unit_path(out / "units", "factor-q").is_file()
    assert not kept.unit_path(out / "units", "dqn").exists()
    return out


@pytest.fixture(scope="module")
def kept_cut(tmp_path_factory) -> Path:
    """One run of ``ARGS`` interrupted when DQN starts (factor-q kept): tests that edit or resume
    it take a copy (``_copy``)."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        return _cut(tmp_path_factory.mktemp("compare") / "cut", monkeypatch)


def _copy(kept_cut: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(kept_cut, tmp_path / "cut"))


def test_an_interrupted_comparison_resumes_to_the_numbers_and_logs_of_a_whole_run(
    whole, kept_cut, tmp_path
):
    cut = _copy(kept_cut, tmp_path)
    code, err = _cli_quiet("compare", "--resume", str(cut))
    assert code == 0, err
    assert "resuming" in err and "1 of 2 units done" in err
    assert not (cut / "units").exists()  # removed once the outputs are written
    assert json.loads((cut / "comparison.json").read_text())["timing"]["units_resumed"] == 1
    assert _files(cut) == _files(whole)


#: ``factorq compare ARGV...`` in a child whose DQN unit (factor-q kept), once it has taken its
#: first gradient steps, touches the file ``argv[1]`` and stalls there: a SIGKILL then lands
#: mid-method, whatever the load (no race against a poll).
STALL_IN_DQN = """
import pathlib, sys, time
from factorq_trainers import cli
from factorq_trainers.commands.compare import command as compare
from factorq_trainers.methods.dqn import DQNConfig
real, trained = compare.run_unit, pathlib.Path(sys.argv[1])
stepped = []
def stall(steps):
    stepped.append(steps)
    if sum(stepped) > DQNConfig().learning_starts:
        trained.touch()
        time.sleep(3600)
def run_unit(config, unit, progress=None):
    return real(config, unit, stall if unit["method"] == "dqn" else progress)
compare.run_unit = run_unit
sys.exit(cli.main(sys.argv[2:]))
"""


def test_sigkill_during_dqn_then_resume_equals_an_uninterrupted_run(tmp_path):
    cut, trained = tmp_path / "cut", tmp_path / "dqn-trained"
    # DQN trains (100 steps past its learning start), in one regime (a unit is a method's batch
    # of regimes)
    steps = str(DQNConfig().learning_starts + 100)
    trains = [{"300": steps, "static,dynamic": "static"}.get(arg, arg) for arg in ARGS]
    child = subprocess.Popen(
        [sys.executable, "-c", STALL_IN_DQN, str(trained), "compare", *trains, "--out", str(cut)],
        cwd=Path(__file__).parents[1],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + patience(300)
    try:
        while time.monotonic() < deadline and child.poll() is None and not trained.exists():
            time.sleep(0.01)
        assert trained.exists() and child.poll() is None, "the child never trained DQN"
        os.kill(child.pid, signal.SIGKILL)  # mid-method: no chance to clean up
    finally:
        child.kill()
        child.wait()
    assert child.returncode == -signal.SIGKILL
    assert kept.unit_path(cut / "units", "factor-q").is_file()
    assert not kept.unit_path(cut / "units", "dqn").exists()
    assert not (cut / "comparison.json").exists()
    code, err = _cli_quiet("compare", "--resume", str(cut))
    assert code == 0, err
    assert "1 of 2 units done" in err
    assert not (cut / "units").exists()  # removed once the outputs are written
    reference = tmp_path / "whole"
    code, err = _cli_quiet("compare", *trains, "--out", str(reference))
    assert code == 0, err
    assert _files(cut) == _files(reference)


def _refused(out: Path, path: Path, *words: str) -> None:
    """``--resume out`` is refused in one line naming ``path`` and ``--force``, before any
    unit runs."""
    code, err = _cli_quiet("compare", "--resume", str(out))
    lines = err.strip().splitlines()
    assert code == cli.EXIT_USAGE and len(lines) == 1, err
    assert str(path) in lines[0] and "--force" in lines[0] and "Traceback" not in err, err
    for word in words:
        assert word in lines[0], lines[0]
    assert not (out / "comparison.json").exists()


def test_a_kept_unit_of_another_config_is_refused(kept_cut, tmp_path, monkeypatch):
    mine = _copy(kept_cut, tmp_path)
    other = _cut(tmp_path / "other", monkeypatch, "--seed", "1")
    path = kept.unit_path(mine / "units", "factor-q")
    shutil.copyfile(kept.unit_path(other / "units", "factor-q"), path)
    _refused(mine, path, "unit file", "was kept for another configuration")


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda trace: trace.update(total_collisions=-999), ("total_collisions holds -999",)),
        (lambda trace: trace.update(total_collisions=float("nan")), ("holds nan",)),
        (lambda trace: trace["steps"].__setitem__(0, -999), ("steps[0] holds -999",)),
        (lambda trace: trace["epsilon"].__setitem__(0, 2.0), ("not a fraction",)),
        (lambda trace: trace.pop("env_steps"), ("lacks 'env_steps'",)),
    ],
    ids=["negative-collisions", "nan-collisions", "negative-path", "epsilon-2", "no-env-steps"],
)
def test_a_kept_unit_edited_and_sealed_again_with_impossible_values_is_refused(
    edit, words, kept_cut, tmp_path
):
    out = _copy(kept_cut, tmp_path)
    path = kept.unit_path(out / "units", "factor-q")
    _reseal(path, lambda record: edit(record["result"]["traces"][0]))
    _refused(out, path, *words)


def test_force_recomputes_a_refused_unit_to_the_numbers_of_a_whole_run(whole, kept_cut, tmp_path):
    out = _copy(kept_cut, tmp_path)
    path = kept.unit_path(out / "units", "factor-q")
    _reseal(path, lambda record: record["result"]["traces"][0].update(total_collisions=-999))
    _refused(out, path, "total_collisions holds -999")
    code, err = _cli_quiet("compare", "--resume", str(out), "--force")
    assert code == 0, err
    assert _files(out) == _files(whole)


def test_a_comparison_resumes_on_a_local_cluster(whole, kept_cut, tmp_path):
    pytest.importorskip("distributed")
    cut = _copy(kept_cut, tmp_path)
    code, err = _cli_quiet("compare", "--resume", str(cut), "--cluster", "local:2")
    assert code == 0, err
    timing = json.loads((cut / "comparison.json").read_text())["timing"]
    assert "2 workers" in timing["where"] and timing["units_resumed"] == 1, timing
    assert _files(cut) == _files(whole)


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda traces: traces.pop(), "its traces are of the experiments"),
        (lambda traces: traces[0]["loss"].pop(), "per-episode fields of different lengths"),
    ],
    ids=["a-trace-removed", "an-episode-cut"],
)
def test_a_kept_unit_whose_traces_do_not_fit_the_run_is_refused_in_one_line(
    edit, words, kept_cut, tmp_path
):
    """What the schema cannot say (how many traces, episodes of equal length): the command's
    ``check_unit`` refuses it in one line naming the file, before any unit runs."""
    out = _copy(kept_cut, tmp_path)
    path = kept.unit_path(out / "units", "factor-q")
    _reseal(path, lambda record: edit(record["result"]["traces"]))
    code, err = _cli_quiet("compare", "--resume", str(out))
    lines = [line for line in err.strip().splitlines() if "error:" in line]
    assert code == cli.EXIT_USAGE and len(lines) == 1 and words in lines[0], err
    assert "--force" in lines[0] and str(path) in lines[0] and "Traceback" not in err
    assert not (out / "comparison.json").exists()
