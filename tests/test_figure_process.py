"""Figure 3 from ``factorq paper``'s helper process: the same bytes as drawn in-process, no torch in
the helper, and a failing or interrupted helper leaves one clear line and no half-written file."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys

import pytest
from test_report import synthetic_results
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.commands.paper import command as paper
from factorq_trainers.commands.paper import figure as paper_figure
from factorq_trainers.commands.paper import figure_process, report
from factorq_trainers.commands.paper.figure_process import FigureProcess, FigureProcessError
from factorq_trainers.compiled import fast
from factorq_trainers.runner import frame
from factorq_trainers.runner.results import temporary_path

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
TINY = ["--seeds", "2", "--runs", "1", "--episodes", "3", "--size", "5", "--obstacles", "3"]


@pytest.fixture(scope="module")
def results():
    return synthetic_results()


def failing_helper(monkeypatch, code: str) -> None:
    """Make ``FigureProcess.start`` run ``python -c code`` instead of the helper."""
    monkeypatch.setattr(figure_process, "command", lambda: [sys.executable, "-c", code])


def output_names(out) -> list[str]:
    return sorted(path.name for path in out.iterdir() if path.name != ".factorq.lock")


@pytest.mark.parametrize("shape", ["small", "defaults"])
def test_the_helper_draws_the_bytes_drawn_in_process(results, shape, tmp_path):
    if shape == "defaults":  # the figure the helper prepared before it was sent the curves
        results = synthetic_results(seeds=100, runs=10, episodes=200)
    report.figure3(results, tmp_path / "here.png")
    with contextlib.closing(FigureProcess.start()) as helper:
        report.send_figure(helper, results, tmp_path)
        temporary = temporary_path(tmp_path / report.FIGURE_FILE)
        helper.finish(temporary)
        assert helper.process.returncode == 0
    assert temporary.read_bytes() == (tmp_path / "here.png").read_bytes()


def test_the_prepared_frame_is_that_of_the_paper_defaults():
    results = {"config": frame.plain(paper.PaperConfig())}
    spec = paper_figure.frame_spec(results, *report.figure_arguments(results))
    assert paper_figure.default_spec() == spec


def test_a_prepared_frame_draws_the_same_bytes(results, tmp_path):
    arguments = report.figure_arguments(results)
    prepared = paper_figure.prepare(paper_figure.frame_spec(results, *arguments))
    paper_figure.draw(results, tmp_path / "prepared.png", *arguments, prepared=prepared)
    other = paper_figure.prepare(paper_figure.default_spec())  # another figure's: not used
    paper_figure.draw(results, tmp_path / "other.png", *arguments, prepared=other)
    report.figure3(results, tmp_path / "fresh.png")
    fresh = (tmp_path / "fresh.png").read_bytes()
    assert (tmp_path / "prepared.png").read_bytes() == fresh
    assert (tmp_path / "other.png").read_bytes() == fresh


def test_the_helper_does_not_import_torch():
    code = (
        "import sys\n"
        "from factorq_trainers.commands.paper import figure as paper_figure\n"
        "paper_figure.preload()\n"
        "paper_figure.warm_up()\n"
        "assert 'torch' not in sys.modules, 'the figure process imported torch'\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=patience(120))


def test_a_helper_that_is_not_sent_anything_is_ended_by_close():
    helper = FigureProcess.start()
    helper.close()
    assert helper.process.poll() is not None  # ended and reaped: no process left behind


def test_finish_names_why_the_helper_failed(results, tmp_path, monkeypatch):
    failing_helper(monkeypatch, "import sys; sys.stderr.write('boom\\n'); sys.exit(3)")
    with contextlib.closing(FigureProcess.start()) as helper:
        report.send_figure(helper, results, tmp_path)
        with pytest.raises(FigureProcessError, match=r"exit 3: boom"):
            helper.finish(temporary_path(tmp_path / report.FIGURE_FILE))


def test_finish_refuses_a_helper_that_exits_0_without_the_file(results, tmp_path, monkeypatch):
    failing_helper(monkeypatch, "import sys; sys.stdin.buffer.read()")
    with contextlib.closing(FigureProcess.start()) as helper:
        report.send_figure(helper, results, tmp_path)
        with pytest.raises(FigureProcessError, match="exited without writing"):
            helper.finish(temporary_path(tmp_path / report.FIGURE_FILE))


def test_ctrl_c_while_the_helper_draws_ends_it_and_leaves_no_file(results, tmp_path, monkeypatch):
    failing_helper(monkeypatch, "import sys, time; sys.stdin.buffer.read(); time.sleep(60)")
    helper = FigureProcess.start()

    def interrupted(*args, **kwargs):
        monkeypatch.undo()  # close() waits for real
        raise KeyboardInterrupt

    monkeypatch.setattr(helper.process, "wait", interrupted)
    with pytest.raises(KeyboardInterrupt):
        frame.write_outputs(paper, results, tmp_path, figure_process=helper)
    assert helper.process.poll() is not None  # ended before the temporaries were removed
    assert output_names(tmp_path) == []
    helper.close()


@needs_fast
def test_a_failed_helper_is_one_notice_and_the_figure_is_drawn_in_process(
    tmp_path, monkeypatch, capsys
):
    failing_helper(monkeypatch, "import sys; sys.stderr.write('no display\\n'); sys.exit(1)")
    out = tmp_path / "paper"
    assert cli.main(["paper", *TINY, "--out", str(out)]) == 0
    err = capsys.readouterr().err
    notices = [line for line in err.splitlines() if "figure process failed" in line]
    assert notices == [
        "factorq: the figure process failed (exit 1: no display); drawing figure3.png here instead"
    ]
    assert output_names(out) == ["figure3.png", "report.md", "results.json"]  # no temporaries
    redrawn = tmp_path / "redrawn.png"
    report.figure3(json.loads((out / "results.json").read_text()), redrawn)
    assert (out / "figure3.png").read_bytes() == redrawn.read_bytes()


@needs_fast
def test_without_a_helper_the_figure_is_drawn_in_process(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(FigureProcess, "start", classmethod(lambda cls: None))
    out = tmp_path / "paper"
    assert cli.main(["paper", *TINY, "--out", str(out)]) == 0
    assert "figure process" not in capsys.readouterr().err
    assert output_names(out) == ["figure3.png", "report.md", "results.json"]


@needs_fast
def test_a_figure_that_cannot_be_drawn_is_one_error_line_and_no_file(tmp_path, monkeypatch, capsys):
    failing_helper(monkeypatch, "import sys; sys.exit(1)")

    def broken(results, path):
        open(path, "wb").write(b"half a PNG")  # noqa: SIM115 - a writer that dies mid-file
        raise RuntimeError("Agg ran out of memory")

    monkeypatch.setattr(report, "figure3", broken)
    out = tmp_path / "paper"
    assert cli.main(["paper", *TINY, "--out", str(out)]) == cli.EXIT_FAILURE
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == (
        "factorq paper: error: drawing figure3.png failed: RuntimeError: Agg ran out of memory"
    )
    assert "Traceback" not in "\n".join(err)
    # nothing written, nothing half-written; the finished units are kept for --resume
    assert output_names(out) == ["units"]
    monkeypatch.undo()
    assert cli.main(["paper", "--resume", str(out)]) == 0
    assert "resuming" in capsys.readouterr().err
    assert output_names(out) == ["figure3.png", "report.md", "results.json"]


@needs_fast
def test_the_command_line_run_writes_the_three_files_with_the_helpers_figure(tmp_path):
    out = tmp_path / "paper"
    process = subprocess.run(
        [sys.executable, "-m", "factorq_trainers.cli", "paper", *TINY, "--out", str(out)],
        capture_output=True,
        timeout=patience(300),
    )
    assert process.returncode == 0, process.stderr.decode()
    assert b"Traceback" not in process.stderr and b"figure process" not in process.stderr
    assert output_names(out) == ["figure3.png", "report.md", "results.json"]
    assert str(out) in process.stdout.decode()  # the output was flushed before the fast exit
    redrawn = tmp_path / "redrawn.png"
    report.figure3(json.loads((out / "results.json").read_text()), redrawn)
    assert (out / "figure3.png").read_bytes() == redrawn.read_bytes()


def test_paper_loads_neither_the_other_commands_nor_matplotlib_in_the_main_process(tmp_path):
    code = (
        "import sys\n"
        "from factorq_trainers import cli\n"
        "assert 'torch' not in sys.modules, 'importing the cli imported torch'\n"
        f"assert cli.main(['paper', '--seeds', '0', '--out', {str(tmp_path)!r}]) == 2\n"
        "loaded = [name for name in ('matplotlib', 'torchrl', 'tensordict',\n"
        "          'factorq_trainers.commands.dependencies.command',\n"
        "          'factorq_trainers.commands.minigrid.command',\n"
        "          'factorq_trainers.commands.compare.command') if name in sys.modules]\n"
        "assert not loaded, loaded\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, timeout=patience(120))
