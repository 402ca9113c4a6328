"""Issue 29 item 1: files the project creates are never opened through links. A link planted
where the lock, a temporary or an output belongs is refused in one line, and its target is left
as it was (the lock used to be opened through the link and the target truncated to a pid)."""

from __future__ import annotations

import os

import pytest

from factorq_trainers.runner import checkpoint, outdir, results

PRECIOUS = b"a user's file, not ours\n"


@pytest.fixture
def victim(tmp_path):
    path = tmp_path / "precious.txt"
    path.write_bytes(PRECIOUS)
    return path


def one_line(error: pytest.ExceptionInfo) -> str:
    message = str(error.value)
    assert "\n" not in message
    return message


def test_a_link_planted_as_the_lock_is_refused_and_its_target_kept(tmp_path, victim):
    out = tmp_path / "out"
    out.mkdir()
    (out / outdir.LOCK_FILE).symlink_to(victim)
    with pytest.raises(outdir.LinkRefused) as error:
        with outdir.claim(out):
            pytest.fail("claimed through a link")
    assert "is a symbolic link where factorq writes its own file" in one_line(error)
    assert outdir.LOCK_FILE in str(error.value)
    assert victim.read_bytes() == PRECIOUS


def test_a_dangling_link_as_the_lock_creates_nothing_at_its_target(tmp_path):
    out, target = tmp_path / "out", tmp_path / "would-be-created"
    out.mkdir()
    (out / outdir.LOCK_FILE).symlink_to(target)
    with pytest.raises(outdir.LinkRefused):
        with outdir.claim(out):
            pass
    assert not target.exists()


def test_a_lock_that_is_not_a_regular_file_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    os.mkfifo(out / outdir.LOCK_FILE)
    with pytest.raises(outdir.OutputDirError, match="is not a regular file: remove it"):
        with outdir.claim(out):
            pass


def test_the_lock_of_a_fresh_and_of_an_earlier_run_is_a_regular_file_with_our_pid(tmp_path):
    out = tmp_path / "out"
    for _ in range(2):  # created new, then reopened (no link)
        with outdir.claim(out) as path:
            (path / "kept").write_text("x")
            assert (path / outdir.LOCK_FILE).read_text() == str(os.getpid())
    assert not (out / outdir.LOCK_FILE).is_symlink()


def test_a_link_where_an_output_belongs_is_refused_even_with_force(tmp_path, victim):
    out = tmp_path / "out"
    out.mkdir()
    (out / "results.json").symlink_to(victim)
    with pytest.raises(outdir.LinkRefused, match="results.json"):
        with outdir.claim(out, outputs=["results.json"], force=True):
            pass
    assert victim.read_bytes() == PRECIOUS


def test_a_link_planted_at_a_temporarys_name_is_refused_and_its_target_kept(tmp_path, victim):
    path = tmp_path / "results.json"
    results.temporary_path(path).symlink_to(victim)
    with pytest.raises(outdir.LinkRefused) as error:
        results.write_atomic(path, lambda temporary: temporary.write_text("{}"))
    one_line(error)
    assert victim.read_bytes() == PRECIOUS
    assert not path.exists()
    # the link was removed with the temporaries: the next write goes through
    results.write_atomic(path, lambda temporary: temporary.write_text("{}"))
    assert path.read_text() == "{}" and victim.read_bytes() == PRECIOUS


def test_a_stale_regular_temporary_of_a_reused_pid_is_replaced(tmp_path):
    path = tmp_path / "results.json"
    results.temporary_path(path).write_text("half-written by a killed run")
    results.write_atomic(path, lambda temporary: temporary.write_text("new"))
    assert path.read_text() == "new"
    assert not results.temporary_path(path).exists()


def test_a_link_planted_at_the_checkpoints_temporary_is_refused_and_its_target_kept(
    tmp_path, victim
):
    out = tmp_path / "out"
    directory = checkpoint.directory_of(out)
    directory.mkdir(parents=True)
    (directory / f".{checkpoint.LATEST}.{os.getpid()}.tmp").symlink_to(victim)
    with pytest.raises(outdir.LinkRefused):
        checkpoint.save(out, {"episodes": 1})
    assert victim.read_bytes() == PRECIOUS
    assert not (directory / checkpoint.LATEST).exists()


def test_a_fifo_where_a_results_file_belongs_is_named_as_such_not_missing(tmp_path):
    from factorq_trainers import reports

    fifo = tmp_path / "results.json"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="results.json is not a regular file: not a results file"):
        results.read_json(fifo, ["config"], "run factorq paper")  # (reading it would block)
    with pytest.raises(ValueError, match="is not a regular file"):
        reports.find(tmp_path)
