"""Issue 29 item 4: every failure while writing is handled. A full disk, a quota or a file size
limit during any save (a checkpoint included: torch's zip writer raises a RuntimeError that names
none of them) gives one line naming the file, keeps what was there (a run's finished units, for
``--resume``), and leaves no half-written file."""

from __future__ import annotations

import errno
import os
import resource
import subprocess
import sys

import pytest
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers.runner import results

#: What torch's zip writer raises when a write comes up short (seen with RLIMIT_FSIZE).
TORCH_SHORT_WRITE = RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704")


def _failing_torch_save(*args, **kwargs):
    raise TORCH_SHORT_WRITE


def _one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


def test_a_failed_results_write_names_the_file_and_keeps_the_old_one(tmp_path):
    path = tmp_path / "results.json"
    path.write_text("old")

    def full_disk(temporary):
        temporary.write_text("half")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(OSError) as error:
        results.write_atomic(path, full_disk)
    assert _one_line(error) == (
        f"cannot write {path}: No space left on device (a full disk, a quota or a file size "
        f"limit?); what was there is kept"
    )
    assert error.value.errno == errno.ENOSPC
    assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == [path.name]


def _limited(limit: int):
    def apply() -> None:  # in the child, before it runs: its files may not grow past ``limit``
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return apply


# Two units (an algorithm each) of some 8 kB kept each, results of some 68 kB.
PAPER = ["--seeds", "3", "--runs", "3", "--episodes", "60", "--size", "6", "--obstacles", "4"]


@pytest.mark.parametrize(
    ("limit", "file", "kept"),
    [(4096, "units/", 0), (2**15, "results.json", 2)],  # a unit's file is some 8 kB, results 68
    ids=["unit", "results"],
)
def test_a_file_size_limit_in_a_real_run_is_one_line_exit_1_and_resumes_from_its_units(
    tmp_path, limit, file, kept
):
    """A real ``factorq paper`` under ``RLIMIT_FSIZE`` (Python ignores SIGXFSZ: the write fails
    with EFBIG): no file half-written, the units finished before it kept for ``--resume``."""
    out = tmp_path / "run"
    command = [sys.executable, "-m", "factorq_trainers.cli", "paper", *PAPER, "--threads", "1"]
    done = subprocess.run(
        [*command, "--out", str(out)],
        preexec_fn=_limited(limit),
        capture_output=True,
        text=True,
        timeout=patience(120),
        cwd=tmp_path,
    )
    error = done.stderr.strip().splitlines()[-1]
    assert done.returncode == 1, done.stderr
    assert error.startswith(f"factorq paper: error: cannot write {out}/{file}"), done.stderr
    assert "Traceback" not in done.stderr
    assert sorted(path.name for path in out.iterdir()) == [".factorq.lock", "units"]
    assert len(list((out / "units").iterdir())) == 1 + kept  # run.json and the finished units
    resumed = subprocess.run(
        [sys.executable, "-m", "factorq_trainers.cli", "paper", "--resume", str(out)],
        capture_output=True,
        text=True,
        timeout=patience(120),
        cwd=tmp_path,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert f"{kept} of 2 units done" in resumed.stderr
    assert sorted(path.name for path in out.iterdir()) == [
        ".factorq.lock",
        "figure3.png",
        "report.md",
        "results.json",
    ]
