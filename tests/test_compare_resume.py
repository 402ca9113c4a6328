"""``factorq compare --checkpoint-every`` (issue 14): a comparison interrupted during a method
resumes from the method's saved state (tables or networks, optimiser, replay buffer, torch's
random state, world, records) and gives the numbers and logs of an uninterrupted run; a changed
config or a tampered state is refused in one line."""

from __future__ import annotations

import contextlib
import io
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
from factorq_trainers.experiments import compare
from factorq_trainers.experiments.dqn import DQNConfig
from factorq_trainers.runner import checkpoint, compare_checkpoint

#: Every method, small: a few hundred env steps of 2 worlds x 2 seeds on a 4 x 4 grid.
SMALL = dict(
    seeds=2,
    steps=240,
    size=4,
    obstacles=1,
    worlds=("static", "dynamic"),
    dqn=DQNConfig(
        learning_starts=20, batch_size=8, buffer_size=64, hidden=(16,), target_update_interval=5
    ),  # fmt: skip
)


class Stop(Exception):
    """Raised from the progress callback: the run is cut between two steps."""


def _numbers(results: dict) -> dict:
    """``comparison.json`` without what measures time (or names the directory)."""
    results = json.loads(json.dumps(results))
    results.pop("timing", None)
    results["config"].pop("out")
    for method in results["results"].values():
        for world in method.values():
            world.pop("wall_s")
    return results


@pytest.mark.parametrize("method", compare.METHODS)
def test_a_method_cut_after_a_mid_method_checkpoint_resumes_to_the_same_numbers(
    method, tmp_path, one_thread
):
    config = compare.CompareConfig(methods=(method,), out=str(tmp_path / "whole"), **SMALL)
    whole = compare.run(config, checkpoints=True, checkpoint_every=1)
    cut = compare.CompareConfig(methods=(method,), out=str(tmp_path / "cut"), **SMALL)

    def progress(name, done, total):
        if done >= total * 3 // 4:
            raise Stop

    with pytest.raises(Stop):
        compare.run(cut, progress, checkpoints=True, checkpoint_every=1)
    resume = compare.load_checkpoint(cut.out)
    assert resume.running is not None and resume.running["method"] == method
    assert 0 < resume.running["state"]["step"] < cut.steps
    resumed = compare.run(cut, checkpoints=True, resume=resume)
    assert _numbers(resumed) == _numbers(whole)


def test_saving_checkpoints_changes_no_number(tmp_path, one_thread):
    config = compare.CompareConfig(methods=("factor-q", "dqn"), out=str(tmp_path / "a"), **SMALL)
    plain = compare.run(config)
    saved = compare.run(config, checkpoints=True, checkpoint_every=1)
    assert _numbers(saved) == _numbers(plain)


def _cli_quiet(*argv: str) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = cli.main(list(argv))
    return code, err.getvalue()


#: A comparison on the command line that runs in seconds; DQN (the second method) is killed.
ARGS = ["--methods", "factor-q,dqn", "--seeds", "1", "--steps", "800", "--size", "4",
        "--obstacles", "1", "--worlds", "static,dynamic", "--threads", "1"]  # fmt: skip


def _files(out: Path) -> dict[str, bytes]:
    """comparison.json and every log file, by path (the figure holds no number the json lacks)."""
    files = {"comparison.json": (out / "comparison.json").read_bytes()}
    for path in sorted((out / "logs").rglob("*")):
        if path.is_file():
            files[str(path.relative_to(out))] = path.read_bytes()
    return files


def _comparable(files: dict[str, bytes]) -> dict[str, object]:
    data = dict(files)
    data["comparison.json"] = _numbers(json.loads(files["comparison.json"]))
    return data


def test_sigkill_during_dqn_then_resume_equals_an_uninterrupted_run(tmp_path):
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    code, err = _cli_quiet("compare", *ARGS, "--out", str(whole))
    assert code == 0, err
    child = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "factorq_trainers.cli",
            "compare",
            *ARGS,
            "--out",
            str(cut),
            "--checkpoint-every",
            "1",
        ],  # fmt: skip
        cwd=Path(__file__).parents[1],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )
    path = cut / checkpoint.DIRECTORY / checkpoint.LATEST
    deadline = time.monotonic() + patience(300)
    saved = None
    try:
        while time.monotonic() < deadline and child.poll() is None:
            with contextlib.suppress(checkpoint.CheckpointError, OSError):
                saved = compare_checkpoint.read(path) if path.exists() else None
            if saved is not None and saved.running and saved.running["method"] == "dqn":
                break
            time.sleep(0.02)
        assert child.poll() is None, "the run ended before a checkpoint during DQN"
        os.kill(child.pid, signal.SIGKILL)  # mid-method: no chance to clean up
    finally:
        child.kill()
        child.wait()
    assert child.returncode == -signal.SIGKILL
    assert not (cut / "comparison.json").exists()
    resume = compare.load_checkpoint(cut)
    assert resume.running["method"] == "dqn" and list(resume.finished) == ["factor-q"]
    code, err = _cli_quiet("compare", "--resume", str(cut))
    assert code == 0, err
    assert "resuming" in err and "dqn at env step" in err
    assert not (cut / checkpoint.DIRECTORY).exists()  # removed once the outputs are written
    assert _comparable(_files(cut)) == _comparable(_files(whole))


def _mid_dqn_checkpoint(out: Path) -> compare_checkpoint.CompareCheckpoint:
    config = compare.CompareConfig(methods=("dqn",), out=str(out), **SMALL)

    def progress(name, done, total):
        if done >= total // 2:
            raise Stop

    with pytest.raises(Stop):
        compare.run(config, progress, checkpoints=True, checkpoint_every=1)
    return compare.load_checkpoint(out)


def test_a_resume_with_another_config_is_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "cut"
    compare.save_checkpoint(
        compare.CompareConfig(
            out=str(out),
            methods=("factor-q", "q-learning"),
            seeds=1,
            steps=60,
            size=4,
            obstacles=1,
            worlds=("static",),
        ),  # fmt: skip
        {},
    )
    code = cli.main(["compare", "--resume", str(out), "--steps", "61"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == cli.EXIT_USAGE and len(err) == 1
    assert "steps=61 given, 60 in the checkpoint" in err[0]
    # ... and through the library: the running state's config is the one it was saved under.
    resume = _mid_dqn_checkpoint(tmp_path / "dqn")
    other = compare.CompareConfig(methods=("dqn",), out=str(tmp_path / "dqn"),
                                  **{**SMALL, "seeds": 1})  # fmt: skip
    with pytest.raises(checkpoint.CheckpointError, match="another config .*seeds=1 given, 2 in"):
        compare.run(other, checkpoints=True, resume=resume)


def _tampered(state: dict, path: str, value) -> dict:
    key, _, rest = path.partition("/")
    copy = dict(state)
    copy[key] = value if not rest else _tampered(state[key], rest, value)
    return copy


#: Entries of a mid-DQN state and a value out of what the run can hold.
TAMPERED = [
    ("step", 10**12),
    ("step", 3),  # not at a collector batch's end
    ("rng", torch.zeros(3, dtype=torch.uint8)),
    ("loss", torch.full((4,), -1.0)),
    ("updates", 10**6),
    ("world_state/cell", torch.full((4,), -100_000)),
    ("carrier/cell", torch.full((4,), 99)),
    ("buffer/_writer", {"_cursor": 70, "_write_count": 70}),
    ("buffer/_storage/_len", 10**9),
    ("recorder/sums/steps", torch.full((4,), float("nan"), dtype=torch.float64)),
    ("optimizer/param_groups", []),
    ("policy/module.1.egreedy.eps", torch.tensor(7.0)),
    ("loss_module/_value_estimator.gamma", torch.tensor(0.5)),
]


@pytest.mark.parametrize(("path", "value"), TAMPERED, ids=[p for p, _ in TAMPERED])
def test_a_tampered_mid_method_state_is_refused_before_use(path, value, tmp_path):
    out = tmp_path / "dqn"
    resume = _mid_dqn_checkpoint(out)
    running = {**resume.running, "state": _tampered(resume.running["state"], path, value)}
    content = {"config": resume.config, "finished": {}, "running": running, "every": "1"}
    checkpoint.remove(out)
    checkpoint.save(out, content, kind=checkpoint.COMPARE_FORMAT)  # signed again
    code, err = _cli_quiet("compare", "--resume", str(out))
    lines = [line for line in err.strip().splitlines() if "error:" in line]
    assert code == cli.EXIT_USAGE and len(lines) == 1, err
    assert "is not usable" in lines[0] and "Traceback" not in err


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ("0", "--checkpoint-every='0' is out of range"),
        ("abc", "--checkpoint-every='abc' is not a number of episodes"),
        ("-5s", "--checkpoint-every='-5s' is out of range"),
    ],
)
def test_a_bad_checkpoint_interval_is_one_line_before_any_work(value, message, tmp_path, capsys):
    out = tmp_path / "out"
    code = cli.main(["compare", "--steps", "10", "--out", str(out), f"--checkpoint-every={value}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == cli.EXIT_USAGE and len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_a_time_interval_saves_mid_method_too(tmp_path, one_thread):
    config = compare.CompareConfig(methods=("q-learning",), out=str(tmp_path / "t"), **SMALL)

    def progress(name, done, total):
        time.sleep(0.002)  # a save is due every 1 ms: one is taken between any two reports
        if done >= total // 2:
            raise Stop

    with pytest.raises(Stop):
        compare.run(config, progress, checkpoints=True, checkpoint_every="0.001s")
    resume = compare.load_checkpoint(config.out)
    assert resume.running["method"] == "q-learning" and resume.every == "0.001s"
    assert _numbers(compare.run(config, checkpoints=True, resume=resume)) == _numbers(
        compare.run(config)
    )


def test_the_memory_estimate_counts_the_checkpoint_copy():
    from factorq_trainers.runner import resources

    config = compare.CompareConfig(methods=("dqn",), seeds=2, steps=5000)
    plain = resources.compare_estimate(config)
    saving = resources.compare_estimate(config, checkpointing=True)
    copy = saving.parts["checkpoint copy"]
    # The replay buffer and networks are copied once, and the records.
    assert copy >= plain.parts["replay buffer"] + plain.parts["networks"]
    assert saving.bytes == plain.bytes + copy
