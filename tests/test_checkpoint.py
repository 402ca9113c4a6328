"""Checkpoints: atomic saves, safe loads, exact resume (in process and after a real SIGKILL),
and one clear error for every damaged or foreign checkpoint."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers import cli
from factorq_trainers.compiled import fast
from factorq_trainers.experiments import paper
from factorq_trainers.experiments.paper_config import PaperConfig
from factorq_trainers.runner import checkpoint
from factorq_trainers.runner.checkpoint_files import CheckpointError
from factorq_trainers.runner.results import dumps as dumps_results

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
# Every episode takes at least 10 steps on a 6x6 grid, so each algorithm needs more than the
# fast driver's first chunk (1000 steps per experiment): a checkpoint falls inside each.
FAST = {"seeds": 3, "runs": 3, "episodes": 60, "size": 6, "obstacles": 4, "threads": 1}
# The modular path costs milliseconds per step: the smallest world that still has obstacles.
MODULAR = {"seeds": 1, "runs": 2, "episodes": 3, "size": 3, "obstacles": 1, "threads": 1}


def numbers(results: dict) -> dict:
    """Everything a resumed run must reproduce: all but the timing and the output directory."""
    results = json.loads(dumps_results(results))
    results.pop("timing")
    results["config"].pop("out")
    return results


def interrupted(config: PaperConfig, stop, monkeypatch, **options) -> checkpoint.Checkpoint:
    """Run ``config`` until a save whose content satisfies ``stop(content)``, then interrupt it
    there as Ctrl-C would; return the checkpoint that ``--resume`` would read."""

    real_save = checkpoint.save

    def save_then_maybe_stop(out, content):
        path = real_save(out, content)
        if stop(content):
            raise KeyboardInterrupt
        return path

    monkeypatch.setattr(checkpoint, "save", save_then_maybe_stop)
    with pytest.raises(KeyboardInterrupt):
        paper.run(config, **options)
    monkeypatch.setattr(checkpoint, "save", real_save)
    return checkpoint.load(config.out)


def running(algorithm: str):
    return lambda content: (content["running"] or {}).get("algorithm") == algorithm


def resumed(out: Path) -> dict:
    saved = checkpoint.load(out)
    return paper.run(paper.resume_config(saved.config, {}, out), resume=saved)


@pytest.fixture(scope="module")
def fast_reference(tmp_path_factory):
    if not fast.is_available():
        pytest.skip("fast backend unavailable")
    return paper.run(PaperConfig(**FAST, out=str(tmp_path_factory.mktemp("reference"))))


@pytest.fixture
def fast_run_dir(tmp_path, monkeypatch):
    """The out directory of a fast run interrupted during Factor-Q, with two checkpoints."""
    if not fast.is_available():
        pytest.skip("fast backend unavailable")
    config = PaperConfig(**FAST, out=str(tmp_path / "run"))
    interrupted(config, running("factor-q"), monkeypatch, checkpoint_every=1)
    return tmp_path / "run"


# --------------------------------------------------------------------------------------------
# The interval


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        (5000, checkpoint.Every(episodes=5000)),
        ("5000", checkpoint.Every(episodes=5000)),
        ("30s", checkpoint.Every(seconds=30.0)),
        ("0.5s", checkpoint.Every(seconds=0.5)),
        ("10m", checkpoint.Every(seconds=600.0)),
        ("1h", checkpoint.Every(seconds=3600.0)),
        (" 2 S ", checkpoint.Every(seconds=2.0)),
    ],
)
def test_checkpoint_every_reads_episodes_or_seconds_with_a_unit(given, expected):
    assert checkpoint.parse_every(given) == expected
    assert checkpoint.parse_every(str(expected)) == expected  # what a checkpoint stores


def test_an_episode_interval_is_due_after_that_many_episodes_summed_over_experiments(tmp_path):
    saver = checkpoint.Checkpointer(tmp_path, {}, "fast", every=10)
    saver.advance(6, 0)
    assert not saver.due()
    saver.advance(4, 1)
    assert saver.due()
    saver.save("factor-q", {"x": torch.zeros(1)})
    assert not saver.due() and saver.saves == 1
    assert not checkpoint.Checkpointer(tmp_path / "other", {}, "fast").due()  # no interval


# --------------------------------------------------------------------------------------------
# Saving and loading


def content(episodes: int) -> dict:
    return {
        "config": {"seed": 0, "worlds": ["static"]},
        "backend": "fast",
        "every": "30s",
        "finished": {"q-learning": {"steps": torch.arange(6).view(1, 2, 3)}},
        "running": {
            "algorithm": "factor-q",
            "state": {
                "q": torch.full((2, 4), 0.25),
                "cell": torch.tensor([3, 7]),
                "bump": torch.tensor([[True, False, False, True]]),
                "task_return": torch.tensor([-1.5], dtype=torch.float32),
            },
        },
        "episodes_completed": episodes,
        "experiments_finished": 1,
        "elapsed_s": 1.25,
        "saved_utc": "2026-01-01T00:00:00Z",
    }


def test_round_trip_keeps_every_field_and_tensor_bit_for_bit(tmp_path):
    path = checkpoint.save(tmp_path, content(7))
    assert path == tmp_path / "checkpoint" / "checkpoint.pt"
    loaded = checkpoint.load(tmp_path)
    original = content(7)
    assert loaded.episodes_completed == 7 and loaded.every == "30s"
    assert checkpoint.digest(loaded._asdict() | {"path": None}) == checkpoint.digest(
        {**original, "path": None}
    )
    state = loaded.running["state"]
    assert state["bump"].dtype == torch.bool and torch.equal(state["cell"], torch.tensor([3, 7]))


def test_save_keeps_the_previous_checkpoint_and_leaves_no_temporaries(tmp_path):
    checkpoint.save(tmp_path, content(1))
    checkpoint.save(tmp_path, content(2))
    checkpoint.save(tmp_path, content(3))
    directory = tmp_path / "checkpoint"
    assert sorted(path.name for path in directory.iterdir()) == [
        "checkpoint.prev.pt",
        "checkpoint.pt",
    ]
    assert checkpoint.read(directory / "checkpoint.pt").episodes_completed == 3
    assert checkpoint.read(directory / "checkpoint.prev.pt").episodes_completed == 2


def test_checkpoint_files_load_with_weights_only_and_hold_plain_data(tmp_path):
    path = checkpoint.save(tmp_path, content(1))
    record = torch.load(path, weights_only=True)  # no pickled code to trust
    assert record["format"] == "factorq-paper-checkpoint" and record["version"] == 1


def test_a_crash_while_writing_leaves_both_old_checkpoints_intact(tmp_path, monkeypatch):
    checkpoint.save(tmp_path, content(1))
    checkpoint.save(tmp_path, content(2))
    directory = tmp_path / "checkpoint"
    before = {path.name: path.read_bytes() for path in directory.iterdir()}

    def half_written_then_crash(obj, file):
        file.write(b"PK\x03\x04 half a zip")
        raise OSError("disk went away")

    monkeypatch.setattr(torch, "save", half_written_then_crash)
    with pytest.raises(OSError, match="disk went away"):
        checkpoint.save(tmp_path, content(3))
    assert {path.name: path.read_bytes() for path in directory.iterdir()} == before


def test_a_crash_between_the_renames_still_leaves_a_complete_newest_checkpoint(
    tmp_path, monkeypatch
):
    checkpoint.save(tmp_path, content(1))
    checkpoint.save(tmp_path, content(2))
    real_replace = os.replace
    calls = []

    def replace_then_crash(source, target):
        calls.append(Path(target).name)
        if Path(target).name == "checkpoint.pt":  # the previous file moved, the newest not yet
            raise KeyboardInterrupt
        real_replace(source, target)

    monkeypatch.setattr(os, "replace", replace_then_crash)
    with pytest.raises(KeyboardInterrupt):
        checkpoint.save(tmp_path, content(3))
    monkeypatch.setattr(os, "replace", real_replace)
    assert calls == ["checkpoint.prev.pt", "checkpoint.pt"]
    assert checkpoint.load(tmp_path).episodes_completed == 2  # the newest is still whole
    directory = tmp_path / "checkpoint"
    assert checkpoint.read(directory / "checkpoint.prev.pt").episodes_completed == 2


def test_stray_temporaries_of_a_killed_save_are_ignored_and_then_removed(tmp_path):
    checkpoint.save(tmp_path, content(1))
    stray = tmp_path / "checkpoint" / ".checkpoint.pt.99999.factorq-tmp"
    stray.write_bytes(b"PK half")
    assert checkpoint.load(tmp_path).episodes_completed == 1
    checkpoint.remove(tmp_path)
    assert not (tmp_path / "checkpoint").exists()


def damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "garbage":
        path.write_bytes(b"\x00garbage" * 100)
    elif how == "flipped bit in a tensor":
        marker = torch.full((2, 4), 0.25).numpy().tobytes()  # content()'s "q", found in the file
        at = data.index(marker) + 5
        path.write_bytes(data[:at] + bytes([data[at] ^ 0x10]) + data[at + 1 :])
    elif how == "a foreign torch file":
        torch.save({"weight": torch.zeros(3)}, path)
    else:
        raise AssertionError(how)


@pytest.mark.parametrize(
    ("how", "reason"),
    [
        ("truncated", "is corrupted or truncated"),
        ("empty", "is corrupted or truncated"),
        ("garbage", "is corrupted or truncated"),
        ("flipped bit in a tensor", "does not match its digest"),
        ("a foreign torch file", "is not a factorq paper checkpoint"),
    ],
)
def test_a_damaged_newest_checkpoint_is_one_error_naming_the_intact_previous_one(
    tmp_path, how, reason
):
    checkpoint.save(tmp_path, content(1))
    checkpoint.save(tmp_path, content(2))
    latest = tmp_path / "checkpoint" / "checkpoint.pt"
    previous = tmp_path / "checkpoint" / "checkpoint.prev.pt"
    kept = previous.read_bytes()
    damage(latest, how)
    with pytest.raises(CheckpointError) as raised:
        checkpoint.load(tmp_path)
    message = str(raised.value)
    assert "\n" not in message and str(latest) in message and reason in message
    assert f"the previous checkpoint {previous} is intact (1 episodes done)" in message
    assert f"mv {latest} {latest}.damaged" in message
    assert previous.read_bytes() == kept  # loading changes nothing on disk
    os.replace(latest, f"{latest}.damaged")  # what the message says to do
    assert checkpoint.load(tmp_path).episodes_completed == 1


def test_with_both_checkpoints_damaged_the_error_says_to_start_again(tmp_path):
    checkpoint.save(tmp_path, content(1))
    checkpoint.save(tmp_path, content(2))
    damage(tmp_path / "checkpoint" / "checkpoint.pt", "truncated")
    damage(tmp_path / "checkpoint" / "checkpoint.prev.pt", "empty")
    with pytest.raises(CheckpointError, match="the previous one is unusable too .* start the run"):
        checkpoint.load(tmp_path)


def test_a_checkpoint_of_a_newer_format_is_refused_with_the_reason(tmp_path):
    path = checkpoint.save(tmp_path, content(1))
    record = torch.load(path, weights_only=True)
    torch.save({**record, "version": 99}, path)
    with pytest.raises(CheckpointError, match="format version 99; this factorq reads version 1"):
        checkpoint.load(tmp_path)


# --------------------------------------------------------------------------------------------
# Exact resume, in process


@needs_fast
@pytest.mark.parametrize(("algorithm", "every"), [("q-learning", 1), ("factor-q", "0.001s")])
def test_fast_run_interrupted_and_resumed_gives_the_same_numbers(
    algorithm, every, fast_reference, tmp_path, monkeypatch
):
    config = PaperConfig(**FAST, out=str(tmp_path))
    saved = interrupted(config, running(algorithm), monkeypatch, checkpoint_every=every)
    assert saved.running["algorithm"] == algorithm
    assert sorted(saved.finished) == (["q-learning"] if algorithm == "factor-q" else [])
    assert 0 < saved.episodes_completed < 2 * 3 * 3 * 3 * 60
    results = resumed(tmp_path)
    assert numbers(results) == numbers(fast_reference)
    assert results["timing"]["checkpoints"]["resumed_at_episode"] == saved.episodes_completed


def test_modular_run_interrupted_and_resumed_gives_the_same_numbers(tmp_path, monkeypatch):
    # Time-based saves land mid-episode in every world: the pending observation, the worlds'
    # state, the policy streams and the tables must all come back exactly.
    reference = paper.run(PaperConfig(**MODULAR, backend="modular", out=str(tmp_path / "ref")))
    config = PaperConfig(**MODULAR, backend="modular", out=str(tmp_path / "run"))

    class Clock:
        """The checkpoints' clock, 0.06 s later at every look: a save every other step, however
        fast the machine runs this small batch (a real 0.1 s could pass after Factor-Q ended)."""

        now = 0.0

        def monotonic(self) -> float:
            self.now += 0.06
            return self.now

        def __getattr__(self, name):
            return getattr(time, name)

    monkeypatch.setattr(checkpoint, "time", Clock())
    saved = interrupted(config, running("factor-q"), monkeypatch, checkpoint_every="0.1s")
    assert saved.backend == "modular" and list(saved.finished) == ["q-learning"]
    assert saved.running["state"]["collector"]["observation"] is not None
    assert numbers(resumed(tmp_path / "run")) == numbers(reference)


@needs_fast
def test_checkpoints_of_a_resumed_run_go_on_and_keep_the_interval(fast_run_dir):
    saved = checkpoint.load(fast_run_dir)
    assert saved.every == "1"
    results = resumed(fast_run_dir)
    assert results["timing"]["checkpoints"]["every"] == "1"
    assert results["timing"]["checkpoints"]["saved"] >= 1


def test_a_checkpoint_whose_state_does_not_fit_the_run_is_refused(tmp_path, monkeypatch):
    if not fast.is_available():
        pytest.skip("fast backend unavailable")
    config = PaperConfig(**FAST, out=str(tmp_path))
    saved = interrupted(config, running("q-learning"), monkeypatch, checkpoint_every=1)
    record = torch.load(saved.path, weights_only=True)
    record["content"]["running"]["state"]["q"] = torch.zeros(1, 2, 3)
    checkpoint.save(tmp_path, record["content"])  # a valid file with a state of another run
    with pytest.raises(CheckpointError, match="does not fit this run: state\\['q'\\] has shape"):
        resumed(tmp_path)


def test_a_checkpoint_written_by_another_backend_is_refused(tmp_path):
    saved = checkpoint.load(checkpoint.save(tmp_path, content(1)).parents[1])
    with pytest.raises(CheckpointError, match="written by the fast backend but this run uses"):
        checkpoint.Checkpointer(tmp_path, {}, "modular", resume=saved)


# --------------------------------------------------------------------------------------------
# The command line


def one_error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("factorq paper: error: ") and "Traceback" not in captured.err
    return lines[0]


@needs_fast
def test_resume_with_a_conflicting_option_names_each_difference(fast_run_dir, capsys):
    args = ["paper", "--resume", str(fast_run_dir), "--seeds", "5", "--epsilon", "0.5"]
    assert cli.main(args) == 2
    line = one_error_line(capsys)
    assert "has a checkpoint of a different config" in line
    assert "--seeds=5 given, 3 in the checkpoint" in line
    assert "--epsilon=0.5 given, 0.01 in the checkpoint" in line
    assert checkpoint.exists(fast_run_dir)  # nothing was touched


@needs_fast
def test_resume_into_another_out_is_refused(fast_run_dir, tmp_path, capsys):
    assert cli.main(["paper", "--resume", str(fast_run_dir), "--out", str(tmp_path / "x")]) == 2
    assert "differs from the resumed directory" in one_error_line(capsys)


@needs_fast
def test_resume_repeating_the_same_options_and_a_new_thread_count_finishes(
    fast_run_dir, fast_reference, capsys
):
    args = ["paper", "--resume", str(fast_run_dir), "--seeds", "3", "--size", "6", "--threads", "2"]
    assert cli.main(args) == 0
    assert "resuming" in capsys.readouterr().err
    results = json.loads((fast_run_dir / "results.json").read_text())
    assert results["config"]["threads"] == 2
    results["config"]["threads"] = 1
    assert numbers(results) == numbers(fast_reference)
    # the run finished: its checkpoints are gone, and resuming again says why
    assert sorted(path.name for path in fast_run_dir.iterdir() if path.name != ".factorq.lock") == [
        "figure3.png",
        "report.md",
        "results.json",
    ]
    assert cli.main(["paper", "--resume", str(fast_run_dir)]) == 2
    assert "its run finished" in one_error_line(capsys)


@needs_fast
def test_a_corrupted_checkpoint_on_the_command_line_is_one_line_exit_2_then_resumable(
    fast_run_dir, fast_reference, capsys
):
    latest = fast_run_dir / "checkpoint" / "checkpoint.pt"
    previous = fast_run_dir / "checkpoint" / "checkpoint.prev.pt"
    kept = previous.read_bytes()
    damage(latest, "truncated")
    assert cli.main(["paper", "--resume", str(fast_run_dir)]) == 2
    line = one_error_line(capsys)
    assert f"checkpoint {latest} is corrupted or truncated" in line
    assert f"the previous checkpoint {previous} is intact" in line
    assert previous.read_bytes() == kept
    latest.rename(latest.with_name("checkpoint.pt.damaged"))
    assert cli.main(["paper", "--resume", str(fast_run_dir)]) == 0
    results = json.loads((fast_run_dir / "results.json").read_text())
    assert numbers(results) == numbers(fast_reference)


@needs_fast
def test_a_new_run_refuses_an_out_holding_an_unfinished_runs_checkpoint(fast_run_dir, capsys):
    assert cli.main(["paper", "--out", str(fast_run_dir), "--checkpoint-every", "10"]) == 2
    line = one_error_line(capsys)
    assert "holds the checkpoint of an unfinished run" in line
    assert f"--resume {fast_run_dir}" in line


@needs_fast
def test_ctrl_c_of_a_checkpointing_run_keeps_the_checkpoint_and_says_how_to_resume(
    tmp_path, capsys, monkeypatch
):
    real_save = checkpoint.save

    def save_then_interrupt(out, content):
        real_save(out, content)
        raise KeyboardInterrupt

    monkeypatch.setattr(checkpoint, "save", save_then_interrupt)
    args = ["paper", *sum(([f"--{k}", str(v)] for k, v in FAST.items()), [])]
    assert cli.main([*args, "--out", str(tmp_path), "--checkpoint-every", "1"]) == 130
    assert f"interrupted (resume it with --resume {tmp_path})" in capsys.readouterr().err
    assert checkpoint.exists(tmp_path) and not (tmp_path / "results.json").exists()


# --------------------------------------------------------------------------------------------
# A real process, really killed

# About 5 s of work on one thread (1.2 M episodes), a checkpoint every 100 k episodes or more:
# here the three kills fall near 410 k (Q-learning), 680 k and 850 k episodes (Factor-Q).
KILLED = ["--seeds", "400", "--runs", "5", "--episodes", "100", "--size", "8", "--threads", "1"]
EVERY = "100000"


def start(cwd: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "factorq_trainers.cli", "paper", *args],
        cwd=cwd,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def newest_identity(out: Path) -> tuple[int, int] | None:
    try:
        stat = (out / "checkpoint" / "checkpoint.pt").stat()
    except FileNotFoundError:
        return None
    return stat.st_ino, stat.st_mtime_ns


@needs_fast
def test_a_run_killed_at_random_moments_and_resumed_writes_the_same_results(tmp_path):
    # The reference runs in this process with the same config (out="run" in both, relative to
    # their own directories), so results.json must match byte for byte up to "timing".
    options = dict(zip(KILLED[::2], KILLED[1::2], strict=True))
    config = PaperConfig(out="run", **{key[2:]: int(value) for key, value in options.items()})
    reference = dumps_results(paper.run(config))
    work = tmp_path / "killed"
    work.mkdir()
    out = work / "run"
    draws = random.Random(6)  # seeded: the same kill points on every test run
    process = start(work, *KILLED, "--out", "run", "--checkpoint-every", EVERY)
    kills = []
    try:
        for _ in range(3):
            # a few new checkpoints of this process, then a random moment of the work after them
            saves, delay = draws.randint(1, 3), draws.uniform(0.0, 0.3)
            for _ in range(saves):
                before = newest_identity(out)
                deadline = time.monotonic() + patience(120)
                while newest_identity(out) == before and process.poll() is None:
                    assert time.monotonic() < deadline, "no new checkpoint in time"
                    time.sleep(0.005)
            time.sleep(delay)
            if process.poll() is not None:  # a machine much faster than this test was made on
                break
            process.send_signal(signal.SIGKILL)
            process.wait(timeout=patience(60))
            assert process.returncode == -signal.SIGKILL
            assert not (out / "results.json").exists()
            saved = checkpoint.load(out)  # whatever the moment, a whole checkpoint is there
            phase = saved.running["algorithm"] if saved.running else "between algorithms"
            kills.append((saves, round(delay, 3), saved.episodes_completed, phase))
            process = start(work, "--resume", "run")
        _, err = process.communicate(timeout=patience(300))
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == 0, err.decode()
    assert b"Traceback" not in err
    episodes = [kill[2] for kill in kills]
    assert episodes and episodes == sorted(episodes) and len(set(episodes)) == len(kills), kills
    text = (out / "results.json").read_text()
    assert text[: text.index('"timing"')] == reference[: reference.index('"timing"')], kills
    assert json.loads(text)["timing"]["checkpoints"]["resumed_at_episode"] == episodes[-1]
    assert sorted(path.name for path in out.iterdir() if path.name != ".factorq.lock") == [
        "figure3.png",
        "report.md",
        "results.json",
    ]
