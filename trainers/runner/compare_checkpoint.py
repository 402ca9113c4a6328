"""``factorq compare``'s checkpoint: the finished methods' traces, saved after each method, and,
with ``--checkpoint-every``, the whole state of the method in progress; their checks on
resume. A method's numbers do not depend on the others, so a resumed comparison skips the finished
methods, continues the running one from its saved state and repeats an uninterrupted one exactly.
The file goes through ``factorq_trainers.runner.checkpoint`` (atomic, digest, safe loading); every
field is checked against the config, and the running state against a fresh state of the method,
before use. The config is read by its fields (this module does not import ``compare``).

Content: ``config``, ``finished`` ({method: {"traces", "wall_s"}}), ``running`` (None between
methods, else ``{"method", "state", "wall_s"}``: the method's state at a step boundary and the
seconds it had run) and ``every`` (the interval the run was started with, or None). The running
state of an online method (tabular Factor-Q, Q-learning, Factor-DQN) is ``{"step", "collector"
(OnlineCollector.state_dict: tables or networks, the policy's stream counters, the optimiser,
counters, the observation the next step acts on), "world_state", "recorder"}``; of DQN ``{"step",
"rng" (torch's global generator: EGreedyModule and the sampler draw from it), "loss", "updates"
(HardUpdate's counter), "world_state", "carrier" (the Collector's next observation), "policy",
"loss_module" (network and target network), "optimizer", "buffer" (ReplayBuffer.state_dict),
"recorder"}``.
"""

from __future__ import annotations

import math
import os
import time
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from factorq_trainers.runner import checkpoint
from factorq_trainers.runner.compare_state_checks import (
    _TRACE_ARRAYS,
    check_step,
    check_trace,
)


class CompareCheckpoint(NamedTuple):
    """A loaded ``factorq compare`` checkpoint: the config, the finished methods' runs and the
    running method's state (None between methods)."""

    path: Path
    config: dict[str, Any]
    finished: dict[str, dict[str, Any]]
    running: dict[str, Any] | None = None
    every: str | None = None

    @property
    def progress(self) -> str:
        done = f"{len(self.finished)} methods done"
        if self.running is not None:
            step = self.running["state"].get("step")
            done += f", {self.running['method']} at env step {step}"
        return done


def save(
    out: str | os.PathLike,
    config: dict[str, Any],
    runs: dict[str, dict[str, Any]],
    running: dict[str, Any] | None = None,
    every: str | None = None,
) -> Path:
    """Save the finished methods' traces (and ``running``: ``{"method", "state", "wall_s"}`` of
    the method in progress) to ``out/checkpoint/`` (``factorq_trainers.runner.checkpoint``)."""
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
    content = {"config": config, "finished": finished, "running": running, "every": every}
    return checkpoint.save(out, content, kind=checkpoint.COMPARE_FORMAT)


#: The fields of a compare checkpoint's content (one written before mid-method checkpoints
#: holds only the first two).
_FIELDS = ("config", "finished", "running", "every")


def read(path: Path) -> CompareCheckpoint:
    """One compare checkpoint file, its fields' types checked (``CheckpointError``)."""
    content = checkpoint.read_content(path, checkpoint.COMPARE_FORMAT)
    config, finished = content.get("config"), content.get("finished")
    running, every = content.get("running"), content.get("every")
    if set(content) not in ({"config", "finished"}, set(_FIELDS)):
        raise checkpoint.CheckpointError(
            f"checkpoint {path} is not usable: it must hold exactly {', '.join(_FIELDS)}, not "
            f"{', '.join(sorted(map(str, content)))}"
        )
    if not isinstance(config, dict) or not isinstance(finished, dict):
        raise checkpoint.CheckpointError(
            f"checkpoint {path} is not usable: it needs a config and the finished methods"
        )
    if running is not None and (
        not isinstance(running, dict)
        or set(running) != {"method", "state", "wall_s"}
        or not isinstance(running["method"], str)
        or not isinstance(running["state"], dict)
        or not isinstance(running["wall_s"], float)
        or not math.isfinite(running["wall_s"])
        or running["wall_s"] < 0
    ):
        raise checkpoint.CheckpointError(
            f"checkpoint {path} is not usable: running must be None or hold exactly a method "
            f"name, its state (a table) and wall_s (a finite number >= 0)"
        )
    if every is not None:
        try:
            if not isinstance(every, str):
                raise TypeError(f"every={every!r} must be text")
            checkpoint.parse_every(every)
        except (ValueError, TypeError) as error:
            raise checkpoint.CheckpointError(f"checkpoint {path} is not usable: {error}") from None
    return CompareCheckpoint(path, config, finished, running, every)


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
        try:  # name the options that differ
            checkpoint.check_same_config(resume.config, saved_form, "this run")
        except ValueError as error:
            refuse(f"it was written by a run of another config ({error})")
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
            converted.append(check_trace(trace, world, index, experiments, refuse))
        resume.finished[method] = {"traces": converted, "wall_s": wall}
    if resume.running is not None:
        pending = [method for method in config.methods if method not in resume.finished]
        if not pending or resume.running["method"] != pending[0]:
            refuse(
                f"running method {resume.running['method']!r} is not the next one to run, "
                f"{pending[0] if pending else None!r}"
            )
        try:  # the step its progress line shows (the whole state: when the method restarts)
            check_step(resume.running["state"], experiments.steps)
        except ValueError as error:
            refuse(f"running {error}")


# --------------------------------------------------------------------------------------------
# Saving during a method, and restoring its state


class Saver(checkpoint.Schedule):
    """When and what a comparison saves: after each method (``save_finished``) and, with an
    interval ``every`` (episodes summed over the experiments, or seconds, as ``factorq paper
    --checkpoint-every``), during a method (``advance``, ``due``, ``save``); on resume, the
    running method's state for its runner (``restore``)."""

    def __init__(
        self,
        out: str | os.PathLike,
        config: dict[str, Any],
        every: checkpoint.Every | str | int | None = None,
        resume: CompareCheckpoint | None = None,
    ) -> None:
        super().__init__(every)
        self.out = out
        self.config = config
        self.resumed = resume
        self.finished: dict[str, dict[str, Any]] = {}
        self._running = None if resume is None else resume.running
        if resume is not None:
            checkpoint.remove_temporaries(checkpoint.directory_of(out))

    def _every(self) -> str | None:
        return None if self.every is None else str(self.every)

    def save(self, method: str, state: dict[str, Any], wall_s: float) -> Path:
        """Save the finished methods and ``method``'s ``state`` (after ``wall_s`` seconds)."""
        started = time.perf_counter()
        running = {"method": method, "state": state, "wall_s": float(wall_s)}
        path = save(self.out, self.config, self.finished, running, self._every())
        self.saved(started)
        return path

    def save_finished(self, runs: dict[str, dict[str, Any]]) -> Path:
        """Save the finished methods ``runs`` (between methods: nothing running)."""
        self.finished = dict(runs)
        path = save(self.out, self.config, self.finished, None, self._every())
        self.saved()
        return path

    def restore(self, method: str, load_state: Callable[[dict[str, Any]], None]) -> float | None:
        """Call ``load_state(state)`` with ``method``'s saved state, if the checkpoint was taken
        during it (once); what it refuses becomes a ``CheckpointError`` naming the file.
        Returns the seconds the method had run before, or None when nothing was restored."""
        running, self._running = self._running, None
        if running is None or self.resumed is None:  # running comes from the resumed file
            return None
        if running["method"] != method:
            raise checkpoint.CheckpointError(
                f"checkpoint {self.resumed.path} was taken during {running['method']!r} but this "
                f"run resumes at {method!r}: it is not this run's checkpoint"
            )
        try:
            load_state(running["state"])
        except (KeyError, ValueError, TypeError, RuntimeError, AttributeError, IndexError) as error:
            raise checkpoint.CheckpointError(
                f"checkpoint {self.resumed.path} is not usable: {error}"
            ) from None
        return running["wall_s"]
