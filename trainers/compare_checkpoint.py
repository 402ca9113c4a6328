"""``factorq compare``'s checkpoint: the finished methods' traces, saved after each method, and
their checks on resume (issue 14). A method's numbers do not depend on the others, so a resumed
comparison skips the finished methods and repeats an uninterrupted one exactly. The file goes
through ``factorq_trainers.checkpoint`` (atomic, digest, safe loading); every field is checked
against the config before use. The config is read by its fields (this module does not import
``compare``).
"""

from __future__ import annotations

import math
import os
import typing
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from factorq_trainers import checkpoint

_TRACE_ARRAYS = {
    "steps": torch.int64,
    "collisions": torch.int64,
    "greedy_collisions": torch.int64,
    "task_return": torch.float64,
    "env_steps": torch.int64,
    "epsilon": torch.float64,
    "loss": torch.float64,
}
_TRACE_TOTALS = (
    "total_collisions",
    "total_greedy_collisions",
    "total_boxed_in_greedy_collisions",
    "total_env_steps",
)


class CompareCheckpoint(NamedTuple):
    """A loaded ``factorq compare`` checkpoint: the config and the finished methods' runs."""

    path: Path
    config: dict[str, Any]
    finished: dict[str, dict[str, Any]]

    @property
    def progress(self) -> str:
        return f"{len(self.finished)} methods done"


def save(out: str | os.PathLike, config: dict[str, Any], runs: dict[str, dict[str, Any]]) -> Path:
    """Save the finished methods' traces to ``out/checkpoint/``
    (``factorq_trainers.checkpoint``)."""
    finished = {}
    for method, run in runs.items():
        traces = [
            {
                key: torch.from_numpy(np.asarray(value)) if key in _TRACE_ARRAYS else value
                for key, value in trace.items()
            }
            for trace in run["traces"]
        ]
        finished[method] = {"traces": traces, "wall_s": float(run["wall_s"])}
    content = {"config": config, "finished": finished}
    return checkpoint.save(out, content, kind=checkpoint.COMPARE_FORMAT)


def read(path: Path) -> CompareCheckpoint:
    """One compare checkpoint file, its fields' types checked (``CheckpointError``)."""
    content = checkpoint.read_content(path, checkpoint.COMPARE_FORMAT)
    config, finished = content.get("config"), content.get("finished")
    if set(content) != {"config", "finished"}:
        raise checkpoint.CheckpointError(
            f"checkpoint {path} is not usable: it must hold exactly a config and the finished "
            f"methods, not {', '.join(sorted(map(str, content)))}"
        )
    if not isinstance(config, dict) or not isinstance(finished, dict):
        raise checkpoint.CheckpointError(
            f"checkpoint {path} is not usable: it needs a config and the finished methods"
        )
    return CompareCheckpoint(path, config, finished)


def load(out: str | os.PathLike) -> CompareCheckpoint:
    """The newest checkpoint of the comparison writing to ``out`` (see ``checkpoint.load``)."""
    return checkpoint.load(out, reader=read)


def check(resume: CompareCheckpoint, config: Any, saved_form: dict[str, Any]) -> None:
    """Refuse (``CheckpointError``, one line) a checkpoint that is not of ``config``'s run or
    whose traces are malformed: every field's type, shape, dtype, range and finiteness."""

    def refuse(what: str) -> typing.NoReturn:
        raise checkpoint.CheckpointError(f"checkpoint {resume.path} is not usable: {what}")

    if resume.config != {**saved_form, "out": resume.config.get("out"),
                         "threads": resume.config.get("threads")}:  # fmt: skip
        refuse("it was written by a run of another config")
    experiments = config.experiments
    labels = experiments.labels
    for method, run in resume.finished.items():
        if method not in config.methods:
            refuse(f"finished method {method!r} is not one of {', '.join(config.methods)}")
        if not isinstance(run, dict) or set(run) != {"traces", "wall_s"}:
            refuse(f"finished[{method!r}] must hold exactly traces and wall_s")
        if not isinstance(run["traces"], list):
            refuse(f"finished[{method!r}]['traces'] must be a list")
        wall = run.get("wall_s")
        if not isinstance(wall, float) or not math.isfinite(wall) or wall < 0:
            refuse(f"finished[{method!r}]['wall_s'] must be a finite number >= 0")
        if len(run["traces"]) != len(labels):
            refuse(f"finished[{method!r}] holds {len(run['traces'])} traces, not {len(labels)}")
        converted = []
        for (world, index), trace in zip(labels, run["traces"], strict=True):
            converted.append(_check_trace(trace, world, index, experiments, refuse))
        resume.finished[method] = {"traces": converted, "wall_s": wall}


def _check_trace(trace, world, index, experiments, refuse) -> dict[str, Any]:
    where = f"the trace of {world}/seed_{index}"
    if (
        not isinstance(trace, dict)
        or trace.get("world") != world
        or (trace.get("seed_index") != index)
    ):
        refuse(f"{where} is missing or out of order")
    known = {"world", "seed_index", *_TRACE_ARRAYS, *_TRACE_TOTALS}
    if set(trace) != known:
        refuse(f"{where} must hold exactly {', '.join(sorted(known))}")
    episodes = None
    out: dict[str, Any] = {"world": world, "seed_index": index}
    for name, dtype in _TRACE_ARRAYS.items():
        value = trace.get(name)
        if not isinstance(value, torch.Tensor) or value.dtype != dtype or value.dim() != 1:
            refuse(f"{where}: {name} must be a 1-d {dtype} tensor")
        episodes = value.numel() if episodes is None else episodes
        if value.numel() != episodes:
            refuse(f"{where}: {name} has {value.numel()} episodes, not {episodes}")
        if bool(torch.isinf(value).any()) or (name != "loss" and bool(torch.isnan(value).any())):
            refuse(f"{where}: {name} holds NaN or infinite values")  # a loss is NaN w/o updates
        out[name] = value.numpy().copy()
    limits = {
        "steps": (1, experiments.max_steps),
        "collisions": (0, experiments.max_steps),
        "greedy_collisions": (0, experiments.max_steps),
        "env_steps": (1, experiments.steps),
        "epsilon": (0.0, 1.0),
        "task_return": (-experiments.max_steps, 0),
    }
    for name, (low, high) in limits.items():
        if episodes and (out[name].min() < low or out[name].max() > high):
            refuse(f"{where}: {name} holds values outside [{low}, {high}]")
    for name in _TRACE_TOTALS:
        value = trace.get(name)
        if not checkpoint_int(value) or not 0 <= value <= experiments.steps:
            refuse(f"{where}: {name} must be an int in [0, {experiments.steps}]")
        out[name] = value
    return out


def checkpoint_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)
