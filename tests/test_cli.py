"""The ``factorq`` command: help, one-line errors with exit 2, an end-to-end run, Ctrl-C."""

from __future__ import annotations

import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import fields

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.compiled import fast

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
TINY = ["--seeds", "2", "--runs", "1", "--episodes", "2", "--size", "5", "--obstacles", "3"]


#: ``factorq`` as a terminal starts it: Python's own Ctrl-C handler whatever this runner's SIGINT
#: disposition (a runner started in the background by a non-interactive shell ignores SIGINT, and
#: its children would inherit that), without a ``preexec_fn`` (unsafe in a process with threads).
_AT_A_TERMINAL = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "from factorq_trainers.cli import main; sys.exit(main(sys.argv[1:]))"
)


def factorq(*args: str, **kwargs) -> subprocess.Popen:
    """``factorq ARGS`` in a subprocess (the module entry point: no installed script needed)."""
    return subprocess.Popen(
        [sys.executable, "-c", _AT_A_TERMINAL, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        **kwargs,
    )


def test_help_lists_both_commands(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "paper" in out and "report" in out


def test_paper_help_has_every_config_field_with_its_doc(capsys):
    assert cli.main(["paper", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())  # undo argparse's line wrapping
    for field in fields(paper.PaperConfig):
        assert "--" + field.name.replace("_", "-") in out
        assert " ".join(field.metadata["doc"].split()[:4]) in out


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--seeds", "0"], "--seeds=0 is out of range: must be in [1, 2147483647]"),
        (["--runs", "-2"], "--runs=-2 is out of range"),
        (["--episodes", "ten"], "argument --episodes: invalid int value: 'ten'"),
        (["--regimes", "static,windy"], "--regimes: 'windy' is unknown"),
        (["--regimes", "static", "--regimes", "static"], "--regimes: static given more than once"),
        (["--methods", "sarsa"], "--methods: 'sarsa' is unknown"),
        (["--size", "3", "--obstacles", "7"], "--obstacles=7 is out of range: must be in [0, 6]"),
        (["--epsilon", "1.5"], "--epsilon=1.5 is out of range: must be in [0.0, 1.0]"),
        (["--g-min", "0"], "--g-min=0.0 is out of range"),
        (["--max-steps", "0"], "--max-steps=0 is out of range"),
        (["--threads", "0"], "--threads=0 is out of range"),
        (["--backend", "gpu"], "argument --backend: invalid choice: 'gpu'"),
    ],
)
def test_invalid_option_prints_one_error_line_and_exits_2(args, message, capsys):
    assert cli.main(["paper", *args]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("factorq paper: error: ") and message in lines[0]
    assert captured.out == ""


def test_out_that_is_an_existing_file_is_an_error(tmp_path, capsys):
    existing = tmp_path / "file.txt"
    existing.write_text("x")
    assert cli.main(["paper", "--out", str(existing)]) == 2
    assert f"--out='{existing}' is an existing file" in capsys.readouterr().err


def test_invalid_option_in_a_real_process_exits_2_without_traceback():
    process = factorq("paper", "--seeds", "-1")
    out, err = process.communicate(timeout=patience(60))
    assert process.returncode == 2
    assert err.decode().strip() == (
        "factorq paper: error: --seeds=-1 is out of range: must be in [1, 2147483647] "
        "(see factorq paper --help)"
    )
    assert b"Traceback" not in err + out


@needs_fast
def test_paper_writes_results_figure_and_report_and_report_regenerates(tmp_path, capsys):
    out = tmp_path / "paper"
    assert cli.main(["paper", *TINY, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    names = sorted(path.name for path in out.iterdir() if path.name != ".factorq.lock")
    assert names == ["figure3.png", "report.md", "results.json"]  # and no temporary files
    assert str(out) in captured.out
    for claim in ("C1", "C2", "C3", "C4", "C5"):  # the report, with its claims table
        assert any(line.startswith(f"| {claim} |") for line in captured.out.splitlines())
    assert captured.out.startswith((out / "report.md").read_text())
    assert "episode" in captured.err  # the progress bar
    (out / "figure3.png").unlink()
    (out / "report.md").unlink()
    assert cli.main(["report", str(out)]) == 0
    assert sorted(path.name for path in out.iterdir() if path.name != ".factorq.lock") == names


def test_report_of_a_directory_without_results_is_an_error(tmp_path, capsys):
    assert cli.main(["report", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "holds no results file of a factorq command" in err and "results.json" in err


def test_interrupt_during_the_run_exits_130_and_writes_no_results(tmp_path, capsys, monkeypatch):
    def interrupted_unit(config, unit, progress=None, world=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(paper, "run_unit", interrupted_unit)
    monkeypatch.setattr(paper, "resolve_backend", lambda config, world=None: "fast")
    out = tmp_path / "paper"
    assert cli.main(["paper", *TINY, "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert f"interrupted (resume it with --resume {out})" in err and "Traceback" not in err
    assert sorted(path.name for path in out.iterdir()) == [".factorq.lock", "units"]


@needs_fast
def test_ctrl_c_stops_a_real_run_cleanly_with_exit_130(tmp_path):
    out = tmp_path / "paper"
    # 1000 seeds: minutes of work, so the run is surely in progress when the signal comes.
    process = factorq(
        "paper",
        "--seeds",
        "1000",
        "--out",
        str(out),
        "--threads",
        "1",
    )
    err = b""
    deadline = time.monotonic() + patience(60)
    while b"episode" not in err and time.monotonic() < deadline:  # the progress bar is up
        ready, _, _ = select.select([process.stderr], [], [], 1.0)
        if ready:
            err += os.read(process.stderr.fileno(), 4096)
    assert b"episode" in err, err
    time.sleep(0.5)
    process.send_signal(signal.SIGINT)
    out_text, rest = process.communicate(timeout=patience(60))
    err += rest
    assert process.returncode == 130
    assert b"interrupted" in err
    assert b"Traceback" not in err + out_text
    assert not (out / "results.json").exists()


@pytest.mark.parametrize(
    "argv, words",
    [
        ("risk --worlds mars", "--worlds: 'mars' is unknown: choose from grid, minigrid, "),
        ("risk --methods foo,dqn", "--methods: 'foo' is unknown: choose from dqn, "),
    ],
)
def test_a_bad_choice_names_the_choices_as_words(argv, words, capsys, tmp_path):
    """Choices are printed as words, never as a Python tuple (issue 38)."""
    from factorq_trainers import cli

    assert cli.main([*argv.split(), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert words in error and "('" not in error and "')" not in error
