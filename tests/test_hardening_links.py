"""Hardening, round three (issue 41, item 2): no write through a directory link, a directory in a
results file's place refused before the run, a full disk at start-up in one line with no lock
left behind, and only factorq's own temporaries removed."""

from __future__ import annotations

import errno
import os

import pytest

from factorq_trainers import cli
from factorq_trainers.runner import outdir, results


@pytest.fixture
def elsewhere(tmp_path):
    """A directory outside ``--out`` that a link points to: it must stay empty."""
    path = tmp_path / "elsewhere"
    path.mkdir()
    return path


@pytest.mark.parametrize("name", outdir.OWN_DIRECTORIES)
def test_a_link_where_factorq_writes_a_folder_is_refused_before_any_work(tmp_path, elsewhere, name):
    out = tmp_path / "out"
    out.mkdir()
    (out / name).symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(outdir.LinkRefused, match=rf"'{out / name}' is a symbolic link"):
        with outdir.claim(out, force=True):
            pytest.fail("claimed an output directory holding a link to another folder")
    assert list(elsewhere.iterdir()) == []


def test_the_folders_claim_guards_are_the_ones_the_commands_write():
    from factorq_trainers.commands.compare import report as compare_report
    from factorq_trainers.distributed import sweep_spec
    from factorq_trainers.runner import kept

    written = {
        sweep_spec.CONFIGS_DIRECTORY,
        kept.UNITS_DIRECTORY,
        compare_report.LOGS_DIRECTORY,
    }
    assert written == set(outdir.OWN_DIRECTORIES)


def test_paper_refuses_a_linked_units_folder_in_one_line(tmp_path, elsewhere, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "units").symlink_to(elsewhere, target_is_directory=True)
    argv = ["paper", "--seeds", "1", "--runs", "1", "--episodes", "2", "--size", "4"]
    code = cli.main([*argv, "--obstacles", "1", "--out", str(out)])
    assert code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "units' is a symbolic link" in lines[-1], lines
    assert list(elsewhere.iterdir()) == []
    assert not (out / "results.json").exists()


def test_a_directory_where_a_results_file_belongs_is_refused_before_the_run_even_with_force(
    tmp_path,
):
    (tmp_path / "results.json").mkdir()
    with pytest.raises(outdir.OutputDirError, match="holds results.json, which is not a regular"):
        with outdir.claim(tmp_path, outputs=("results.json", "logs"), force=True):
            pytest.fail("the run would have started")
    (tmp_path / "results.json").rmdir()
    (tmp_path / "logs").mkdir()  # compare's logs are a folder: replaced by --force
    with outdir.claim(tmp_path, outputs=("results.json", "logs"), force=True):
        pass


def test_an_atomic_write_refuses_a_link_at_its_destination(tmp_path):
    victim = tmp_path / "victim.md"
    victim.write_text("mine")
    (tmp_path / "report.md").symlink_to(victim)
    with pytest.raises(outdir.LinkRefused, match="report.md' is a symbolic link"):
        results.write_atomic(tmp_path / "report.md", lambda path: path.write_text("new"))
    assert (tmp_path / "report.md").is_symlink() and victim.read_text() == "mine"


def test_report_refuses_a_linked_report_instead_of_replacing_it(tmp_path):
    from factorq_trainers import reports

    (tmp_path / "dependencies.json").write_text(
        '{"schema_version": 1, "command": "dependencies", "config": {}}'
    )
    victim = tmp_path / "victim.md"
    victim.write_text("mine")
    (tmp_path / "dependencies.md").symlink_to(victim)
    with pytest.raises(outdir.LinkRefused):
        reports.regenerate(tmp_path)
    assert (tmp_path / "dependencies.md").is_symlink() and victim.read_text() == "mine"


def _full_disk(monkeypatch, after: int = 0):
    """``os.write`` in ``outdir`` failing with ENOSPC after ``after`` successful calls."""
    calls = []
    original = os.write

    def write(descriptor, data):
        calls.append(descriptor)
        if len(calls) > after:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return original(descriptor, data)

    monkeypatch.setattr(outdir.os, "write", write)


@pytest.mark.parametrize("after", [0, 1])  # the probe's byte, or the lock's pid
def test_a_full_disk_at_start_up_is_one_line_and_leaves_nothing(tmp_path, monkeypatch, after):
    out = tmp_path / "new"
    _full_disk(monkeypatch, after)
    with pytest.raises(outdir.OutputDirError) as error:
        with outdir.claim(out):
            pytest.fail("claimed a full disk")
    monkeypatch.undo()
    assert "is not writable: No space left on device" in str(error.value)
    assert "\n" not in str(error.value)
    assert not out.exists()  # neither the directory it made nor an empty lock


def test_a_full_disk_in_an_existing_directory_leaves_no_new_file(tmp_path, monkeypatch):
    _full_disk(monkeypatch)
    with pytest.raises(outdir.OutputDirError, match="No space left on device"):
        with outdir.claim(tmp_path):
            pass
    monkeypatch.undo()
    assert list(tmp_path.iterdir()) == []


def test_only_factorq_temporaries_are_removed(tmp_path):
    users = [tmp_path / ".backup.2024.tmp", tmp_path / ".notes.12.tmp"]
    users[0].mkdir()
    (users[0] / "kept.txt").write_text("mine")
    users[1].write_text("mine")
    ours = tmp_path / outdir.temporary_name("results.json", 99999)
    ours.write_text("partial")
    staging = tmp_path / outdir.temporary_name("logs", 99999)
    staging.mkdir()
    with outdir.claim(tmp_path):
        pass
    assert all(path.exists() for path in users) and (users[0] / "kept.txt").exists()
    assert not ours.exists() and not staging.exists()
    assert results.temporary_path(tmp_path / "x.json").name.endswith(outdir.TEMPORARY_SUFFIX)
