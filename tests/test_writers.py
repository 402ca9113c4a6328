"""One writer per --out, seen from the command line with real processes (issue 14, item 4):
a second run and a --resume of a live run are refused with the holder's pid; once the holder is
killed, the lock is gone and the run resumes; factorq compare writes its files as a set."""

from __future__ import annotations

import contextlib
import io
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.compare import report as compare_report
from factorq_trainers.compiled import fast

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
# Some seconds of work on one thread, in 32 units (each kept in OUT/units/ as it finishes).
LIVE = ["--seeds", "400", "--runs", "5", "--episodes", "100", "--size", "8", "--threads", "1"]
LIVE += ["--shard-seeds", "25"]


def factorq(*args: str) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(list(args))
    return code, err.getvalue()


@needs_fast
def test_a_live_run_owns_its_out_until_it_dies(tmp_path):
    out = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-m", "factorq_trainers.cli", "paper", *LIVE, "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    try:
        deadline = time.monotonic() + patience(120)
        while len(list(out.glob("units/*.json"))) < 2:  # run.json and a finished unit
            assert process.poll() is None and time.monotonic() < deadline, "no unit kept"
            time.sleep(0.01)
        holder = f"in use by another factorq run (pid {process.pid})"
        code, err = factorq("paper", "--seeds", "1", "--out", str(out))
        assert code == 2 and holder in err and "refusing to write to it" in err, err
        code, err = factorq("paper", "--resume", str(out))
        assert code == 2 and holder in err and "refusing to resume it" in err, err
        code, err = factorq("paper", "--seeds", "1", "--out", str(out), "--force")
        assert code == 2 and holder in err, err  # --force replaces results, never a live run
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=patience(60))
    # SIGKILL releases the lock with the process: the killed run resumes to its end.
    code, err = factorq("paper", "--resume", str(out))
    assert code == 0, err
    results = json.loads((out / "results.json").read_text())
    assert results["config"]["seeds"] == 400 and results["timing"]["units_resumed"] >= 1


@needs_fast
def test_results_are_replaced_only_with_force(tmp_path):
    out = tmp_path / "paper"
    tiny = ["paper", "--seeds", "1", "--runs", "1", "--episodes", "2", "--out", str(out)]
    assert factorq(*tiny)[0] == 0
    before = (out / "results.json").read_bytes()
    code, err = factorq(*tiny, "--seed", "1")
    assert code == 2 and "already holds results.json, report.md, figure3.png" in err
    assert (out / "results.json").read_bytes() == before
    assert factorq(*tiny, "--seed", "1", "--force")[0] == 0
    assert json.loads((out / "results.json").read_text())["config"]["seed"] == 1


def test_stale_temporaries_of_a_killed_writer_are_removed(tmp_path):
    out = tmp_path / "compare"
    (out / ".logs.99999.factorq-tmp" / "q-learning").mkdir(parents=True)
    (out / ".comparison.json.99999.factorq-tmp").write_text("{half")
    args = ["compare", "--methods", "q-learning", "--seeds", "1", "--steps", "30"]
    code, err = factorq(*args, "--size", "4", "--obstacles", "1", "--out", str(out))
    assert code == 0, err
    names = sorted(path.name for path in out.iterdir())
    assert names == [".factorq.lock", "comparison.json", "comparison.md", "comparison.png", "logs"]


def test_compare_replaces_its_files_and_logs_as_a_set(tmp_path, monkeypatch):
    out = tmp_path / "compare"
    args = ["compare", "--methods", "q-learning", "--seeds", "1", "--steps", "40", "--size", "4"]
    args += ["--obstacles", "1", "--out", str(out)]
    assert factorq(*args)[0] == 0
    first = {path: path.read_bytes() for path in sorted(out.rglob("*")) if path.is_file()}
    logged = sorted(out.glob("logs/q-learning/scalars/*/seed_0/path_length.csv"))
    assert logged, sorted(out.rglob("*"))

    # A run killed while its files are written leaves the first run's files, all of them.
    def killed(results, path):
        raise KeyboardInterrupt

    monkeypatch.setattr(compare_report, "figure", killed)  # what the frame draws with
    assert factorq(*args, "--seed", "1", "--force")[0] == 130
    now = {path: path.read_bytes() for path in sorted(out.rglob("*")) if path.is_file()}
    kept_units = {path for path in now if path.parent.name == "units"}  # to resume it
    assert {path: now[path] for path in now if path not in kept_units} == first  # no temporary
    assert kept_units

    # A finished second run replaces every file, the logs included: no row of the first run.
    monkeypatch.undo()
    assert factorq(*args, "--seed", "1", "--force")[0] == 0
    assert json.loads((out / "comparison.json").read_text())["config"]["seed"] == 1
    rows = [path.read_text().splitlines() for path in logged]
    assert all(len(lines) == len(set(lines)) for lines in rows)  # nothing appended twice
    assert not [path for path in out.iterdir() if path.name.endswith("tmp")]
    assert Path(out / "logs").is_dir()


@needs_fast
def test_a_finished_sweep_is_replaced_only_with_force(tmp_path):
    out = tmp_path / "sweep"
    args = ["sweep", "--grid", "eta=0.05,0.1", "--set", "runs=1", "--set", "episodes=3"]
    args += ["--set", "size=4", "--set", "obstacles=1", "--seeds", "2", "--out", str(out)]
    assert factorq(*args)[0] == 0
    before = (out / "sweep.json").read_bytes()
    code, err = factorq(*args)
    assert code == 2 and "already holds sweep.json, sweep.md from an earlier run" in err, err
    assert "--out=" in err and len(err.strip().splitlines()) == 1
    assert (out / "sweep.json").read_bytes() == before
    assert factorq(*args, "--force")[0] == 0  # its shards are reused: the same numbers
    assert json.loads((out / "sweep.json").read_text())["configurations"]
