"""One writer per output directory (trainers/runner/outdir.py)."""

import os
import subprocess
import sys
import textwrap

import pytest

from factorq_trainers.runner.outdir import LOCK_FILE, OutputDirError, claim


def hold_lock_in_another_process(out):
    """Start a process that claims ``out`` and waits; return it once it holds the lock."""
    script = textwrap.dedent(
        f"""
        import sys, time
        from factorq_trainers.runner.outdir import claim
        with claim({str(out)!r}):
            print("held", flush=True)
            sys.stdin.readline()
        """
    )
    holder = subprocess.Popen(
        [sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    assert holder.stdout.readline().strip() == "held"
    return holder


def test_claim_creates_the_directory_and_yields_it(tmp_path):
    out = tmp_path / "a" / "b"
    with claim(out) as path:
        assert path == out and out.is_dir()


def test_a_second_writer_is_refused_with_the_holders_pid(tmp_path):
    holder = hold_lock_in_another_process(tmp_path)
    try:
        with pytest.raises(
            OutputDirError, match=rf"in use by another factorq run \(pid {holder.pid}\)"
        ):
            with claim(tmp_path):
                pass
        with pytest.raises(OutputDirError, match="refusing to resume it at the same time"):
            with claim(tmp_path, resume=True):
                pass
    finally:
        holder.communicate("\n")
    with claim(tmp_path):  # the holder has finished: free again
        pass


def test_a_killed_holder_leaves_no_stale_lock(tmp_path):
    holder = hold_lock_in_another_process(tmp_path)
    holder.kill()
    holder.wait()
    with claim(tmp_path):
        assert (tmp_path / LOCK_FILE).read_text() == str(os.getpid())


def test_the_lock_is_released_when_the_block_raises(tmp_path):
    with pytest.raises(RuntimeError), claim(tmp_path):
        raise RuntimeError("boom")
    with claim(tmp_path):
        pass


def test_an_out_under_a_file_is_refused_before_any_work(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputDirError, match=r"out='.*file/sub' is not writable: Not a directory"):
        with claim(tmp_path / "file" / "sub"):
            raise AssertionError("the body must not run")


def test_an_out_that_is_a_file_is_refused(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputDirError, match="is not a directory"):
        with claim(tmp_path / "file"):
            pass


def test_an_out_on_a_pseudo_file_system_is_refused():
    with pytest.raises(OutputDirError, match=r"out='/proc/factorq-test' is not writable"):
        with claim("/proc/factorq-test"):
            pass


def test_existing_results_are_kept_unless_forced_or_resumed(tmp_path):
    (tmp_path / "results.json").write_text("{}")
    with pytest.raises(OutputDirError, match="already holds results.json .* pass --force"):
        with claim(tmp_path, outputs=("results.json", "report.md")):
            pass
    assert (tmp_path / "results.json").read_text() == "{}"
    with claim(tmp_path, outputs=("results.json",), force=True):
        pass
    with claim(tmp_path, outputs=("results.json",), resume=True):
        pass


def test_stale_temporaries_of_killed_writers_are_removed(tmp_path):
    stale = tmp_path / ".results.json.12345.factorq-tmp"
    stale.write_text("partial")
    kept = tmp_path / "notes.tmp"
    kept.write_text("mine")
    with claim(tmp_path):
        assert not stale.exists()
        assert kept.exists()
