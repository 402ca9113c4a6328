"""Untrusted checkpoints (issue 14, item 5): every field of a real checkpoint, mutated and signed
again (its SHA-256 proves integrity, not origin), is refused by ``factorq paper --resume`` with
one line and exit 2, never a crash, a traceback or a run on a bad state.

The attempts run in one child process (``fuzz_child``), one JSON line each, so that a crash of
native code (SIGSEGV) fails this test naming the mutation instead of killing pytest.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from timing import patience  # tests/timing.py: bounds that stretch with the load

from factorq_trainers.compiled import fast
from factorq_trainers.experiments.paper import PaperConfig, run
from factorq_trainers.runner import checkpoint

needs_fast = pytest.mark.skipif(not fast.is_available(), reason="fast backend unavailable")
#: A checkpoint taken during Factor-Q with Q-learning finished: every kind of field is there.
CONFIG = dict(seeds=2, runs=3, episodes=100, size=6, obstacles=3, threads=1)
#: Fields whose other values are harmless (they do not change the numbers, or are only shown):
#: a mutation there may also be accepted (exit 0).
HARMLESS = (
    "saved_utc",
    "elapsed_s",
    "every",
    "config/threads",
    "config/out",
)
#: Config fields that enter neither the saved state's shapes nor its keys: another valid value
#: is a checkpoint of another valid run, which resumes (the digest proves no origin).
OTHER_RUN = ("config/max_steps", "config/epsilon", "config/gamma", "config/alpha", "config/eta",
             "config/g_min", "config/backend", "config/device", "config/sensor_permutation",
             "config/sensor_noise", "config/actuator_noise")  # fmt: skip


def mutations(value):
    """``(name, mutated value)`` pairs for one field."""
    if isinstance(value, torch.Tensor):
        yield "as list", value.tolist()
        yield "as int", 5
        if value.numel() > 1:
            yield "shape", value.reshape(-1)[:-1].clone()
        elif value.numel() == 1:
            yield "shape", value.reshape(1, 1)
        yield "extra dim", value.unsqueeze(0).clone()
        other = torch.float64 if value.dtype != torch.float64 else torch.float32
        yield f"dtype {other}", value.to(other)
        if value.numel() == 0 or value.dtype == torch.bool:
            return
        if value.is_floating_point():
            for bad in (math.nan, math.inf, -math.inf):
                mutated = value.clone()
                mutated.view(-1)[0] = bad
                yield f"[0]={bad}", mutated
        else:
            for bad in (-100_000, -(10**9), 10**12, 2**62):
                mutated = value.clone()
                try:
                    mutated.view(-1)[0] = bad
                except RuntimeError:  # not representable in its dtype (uint8: torch's rng state)
                    mutated.view(-1)[0] = torch.iinfo(value.dtype).max - value.view(-1)[0]
                yield f"[0]={bad}", mutated
    elif isinstance(value, dict):
        if value:
            yield "key removed", dict(list(value.items())[1:])
        yield "key added", {**value, "surplus": 1}
        yield "as list", list(value)
    elif isinstance(value, list):
        yield "empty", []
        yield "as dict", {"a": 1}
        yield "as int", 7
    elif isinstance(value, bool):
        yield "as int", 2
    elif isinstance(value, int):
        for bad in (-100_000, -(10**9), 10**12, 2**64, 2.5, "5", None):
            yield f"={bad!r}", bad
    elif isinstance(value, float):
        for bad in (math.nan, math.inf, -1.0, "1.0", None):
            yield f"={bad!r}", bad
    elif isinstance(value, str):
        for bad in ("", "x" * 300, 5, None, ["a"]):
            yield f"={bad!r}", bad
    elif value is None:
        yield "as int", 5
        yield "as str", "x"


def fields_of(tree, path=""):
    """``(path, value)`` of every field and container of a checkpoint's content."""
    yield path, tree
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from fields_of(value, f"{path}/{key}" if path else str(key))


def replaced(tree, path: str, value):
    if not path:
        return value
    key, _, rest = path.partition("/")
    copy = dict(tree)
    copy[key] = replaced(tree[key], rest, value)
    return copy


def without_figures(patch) -> None:
    """Draw no figure (``patch(owner, name, value)`` is ``setattr`` or pytest's ``monkeypatch``):
    an accepted mutation finishes the run, and its figure (a helper process loading matplotlib,
    then the drawing) would cost more than the resume being fuzzed; the figures have their tests.
    """
    from factorq_trainers.reports import compare_report, report
    from factorq_trainers.reports.figure_process import FigureProcess

    def placeholder(results, path) -> None:
        Path(path).write_bytes(b"")

    patch(FigureProcess, "start", classmethod(lambda cls: None))
    patch(report, "figure3", placeholder)
    patch(compare_report, "write_figure", placeholder)


def fuzz_child(out: str) -> None:
    """Run in the child: mutate, sign, resume; print one JSON line per attempt."""
    from factorq_trainers import cli

    without_figures(setattr)

    path = Path(out) / "checkpoint" / checkpoint.LATEST
    original = torch.load(path, weights_only=True)["content"]
    attempts = [
        (field, name, mutated)
        for field, value in fields_of(original)
        for name, mutated in mutations(value)
    ]
    for field, name, mutated in attempts:
        content = replaced(original, field, mutated)
        (Path(out) / "checkpoint").mkdir(exist_ok=True)
        for stale in (Path(out) / "checkpoint").iterdir():
            stale.unlink()
        for result in ("results.json", "figure3.png", "report.md"):
            (Path(out) / result).unlink(missing_ok=True)
        print(json.dumps({"field": field, "mutation": name, "started": True}), flush=True)
        checkpoint.save(out, content)  # signed again: a valid digest
        err = io.StringIO()
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                code = cli.main(["paper", "--resume", out])
            except BaseException as error:  # noqa: BLE001 - report, do not die
                code = f"raised {type(error).__name__}: {error}"
        print(json.dumps({"field": field, "mutation": name, "code": code, "err": err.getvalue()}),
              flush=True)  # fmt: skip


#: The modular path's checkpoint, smaller: an accepted (harmless) mutation runs the rest.
MODULAR = dict(seeds=1, runs=2, episodes=4, size=4, obstacles=1, backend="modular")


@pytest.mark.parametrize(
    ("config", "every"),
    [pytest.param(CONFIG, 10, marks=needs_fast, id="fast"), pytest.param(MODULAR, 2, id="modular")],
)
def test_every_field_of_a_signed_checkpoint_mutated_is_refused_cleanly(config, every, tmp_path):
    out = tmp_path / "run"
    run(PaperConfig(out=str(out), **config), checkpoint_every=every)
    saved = checkpoint.load(out)
    assert saved.running is not None and saved.finished, "the checkpoint lacks a kind of field"
    child = subprocess.run(
        [sys.executable, "-c", f"import {__name__} as t; t.fuzz_child({str(out)!r})"],
        cwd=Path(__file__).parent,
        capture_output=True,
        text=True,
        timeout=patience(900),
    )
    lines = [json.loads(line) for line in child.stdout.splitlines() if line.startswith("{")]
    assert lines, child.stderr[-3000:]
    last = lines[-1]
    assert child.returncode == 0 and "code" in last, (
        f"the child died ({child.returncode}) on {last['field']} {last['mutation']}: "
        f"{child.stderr[-2000:]}"
    )
    results = [line for line in lines if "code" in line]
    failures = []
    for result in results:
        lines_err = result["err"].strip().splitlines()
        harmless = result["field"].startswith(HARMLESS + OTHER_RUN)
        # One error line, the last: a refusal by the backend's loader comes after the lines
        # saying what is resumed.
        errors = [line for line in lines_err if "error:" in line]
        clean_refusal = result["code"] == 2 and len(errors) == 1 and errors[0] == lines_err[-1]
        clean_refusal = clean_refusal and "Traceback" not in result["err"]
        if not (clean_refusal or (harmless and result["code"] == 0)):
            failures.append(f"{result['field']} {result['mutation']}: {result['code']} {lines_err}")
    assert not failures, f"{len(failures)} of {len(results)}:\n" + "\n".join(failures[:40])
    assert len(results) > 200  # every field, several ways


#: Fields of the kernel's state and a value out of its buffers' range, set behind
#: ``load_state_dict``'s back: the kernel itself refuses them (never an out-of-bounds access).
KERNEL_STATE = [
    ("cell", -100_000),
    ("cell", 10**12),
    ("run", -100_000),
    ("episode", 10**12),
    ("episode", -(10**9)),
    ("episode_step", -5),
    ("episode_step", 10**12),
    ("scatters", -1),
    ("policy_counter", -1),
    ("periods", -3),
    ("obstacle_pads", -7),
    ("obstacle_pads", 10**6),
    ("heading", 9),
    ("ticks", -1),
    ("kappa", -2),
    ("episode_collisions", -1),
]


@needs_fast
@pytest.mark.parametrize(
    ("field", "value"), KERNEL_STATE, ids=[f"{f}={v}" for f, v in KERNEL_STATE]
)
@pytest.mark.parametrize("threads", [1, 2])
def test_the_kernel_refuses_a_state_out_of_range_whatever_its_source(field, value, threads):
    from factorq_envs.grid_world import WorldConfig
    from factorq_torch.base.config import AgentConfig
    from factorq_torch.base.rng import STREAM_POLICY, STREAM_WORLD, derive_keys

    batch = fast.ExperimentBatch(
        "factor-q",
        torch.tensor([0, 1, 1]),
        WorldConfig(size=5, num_obstacles=3),
        AgentConfig(),
        2,
        3,
        derive_keys(0, STREAM_WORLD, 3),
        derive_keys(0, STREAM_POLICY, 3),
        threads=threads,
    )
    batch.advance(7)
    batch._tensors[field][-1].view(-1)[-1] = value  # the last experiment's (or its last entry)
    with pytest.raises(ValueError, match=rf"the fast kernel refused experiment 2: its {field} is"):
        batch.advance(1_000)
