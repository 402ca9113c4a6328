"""Checkpoints of ``factorq paper`` and ``factorq compare`` during a run: when one is due
(``Schedule``, kept by paper's ``Checkpointer`` and compare's ``Saver``), paper's
``Checkpointer`` (a run's position, saving, restoring), and the config a resumed run takes
(``resumed_config``). The file format, saving, reading and loading are
``factorq_trainers.runner.checkpoint_files``' (its names are re-exported here).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from factorq_trainers.runner.checkpoint_files import (  # noqa: F401 - the checkpoint names
    COMPARE_FORMAT,
    DIRECTORY,
    FORMAT,
    FORMAT_VERSION,
    LATEST,
    PREVIOUS,
    Checkpoint,
    CheckpointError,
    Every,
    check_none_in,
    digest,
    directory_of,
    exists,
    is_int,
    load,
    parse_every,
    read,
    read_content,
    remove,
    remove_temporaries,
    save,
    to_device,
)

# --------------------------------------------------------------------------------------------
# Saving during a run


class Schedule:
    """When the next checkpoint is due: every ``every`` episodes (summed over the experiments)
    or seconds since the last save (``parse_every``; None: never), and what saving has cost.
    ``factorq paper``'s ``Checkpointer`` and ``factorq compare``'s ``Saver`` both keep it."""

    def __init__(self, every: Every | str | int | None = None) -> None:
        self.every = None if every is None else parse_every(every)
        self.saves = 0
        self.save_seconds = 0.0
        self._last_save = time.monotonic()
        self._episodes_since_save = 0

    def advance(self, episodes: int) -> None:
        """Count ``episodes`` more finished (summed over the experiments)."""
        self._episodes_since_save += episodes

    def due(self) -> bool:
        """Whether a checkpoint is due now (always False without an interval)."""
        if self.every is None:
            return False
        if self.every.episodes is not None:
            return self._episodes_since_save >= self.every.episodes
        seconds = self.every.seconds  # an interval has episodes or seconds
        return seconds is not None and time.monotonic() - self._last_save >= seconds

    def saved(self, started: float | None = None) -> None:
        """A save just ended (begun at ``perf_counter()`` ``started``, if counted): the
        schedule starts over."""
        if started is not None:
            self.saves += 1
            self.save_seconds += time.perf_counter() - started
        self._last_save = time.monotonic()
        self._episodes_since_save = 0


class Checkpointer(Schedule):
    """A run's position (episodes, experiments, finished algorithms), when to save, and saving.

    ``paper.run`` makes one per run (``every=None``: never saves) and counts progress through it;
    a driver asks ``resume_state(algorithm)`` once, then after each chunk of work calls
    ``due()`` and, when it says so, ``save(algorithm, state)``.
    """

    def __init__(
        self,
        out: str | os.PathLike,
        config: dict[str, Any],
        backend: str,
        every: Every | str | int | None = None,
        resume: Checkpoint | None = None,
    ) -> None:
        super().__init__(every)
        self.out = Path(out)
        self.config = config
        self.backend = backend
        self.resumed = resume
        self.finished: dict[str, dict[str, torch.Tensor]] = {}
        self.episodes_completed = 0
        self.experiments_finished = 0
        self._elapsed_before = 0.0
        self._running = None
        if resume is None:
            check_none_in(self.out)
        else:
            if resume.backend != backend:
                raise CheckpointError(
                    f"checkpoint {resume.path} was written by the {resume.backend} backend but "
                    f"this run uses the {backend} one: resume with --backend {resume.backend}"
                )
            self.finished = dict(resume.finished)
            self._running = resume.running
            self.episodes_completed = resume.episodes_completed
            self.experiments_finished = resume.experiments_finished
            self._elapsed_before = resume.elapsed_s
            remove_temporaries(directory_of(self.out))  # of saves cut short by the interruption
        self._started = time.perf_counter()
        self.saved()  # the interval counts from the start

    @property
    def elapsed_s(self) -> float:
        """Seconds of work on this run, in this process and the ones it resumed."""
        return self._elapsed_before + time.perf_counter() - self._started

    def advance(self, episodes: int, experiments: int = 0) -> None:
        """Count ``episodes`` more completed and ``experiments`` more finished."""
        self.episodes_completed += episodes
        self.experiments_finished += experiments
        super().advance(episodes)

    def resume_state(self, algorithm: str) -> dict[str, Any] | None:
        """The saved state of ``algorithm``'s experiments if the checkpoint was taken during
        them (once: later calls return None)."""
        running, self._running = self._running, None
        if running is None or self.resumed is None:  # running comes from the resumed file
            return None
        if running.get("algorithm") != algorithm:
            raise CheckpointError(
                f"checkpoint {self.resumed.path} was taken during {running.get('algorithm')!r} "
                f"but this run resumes at {algorithm!r}: it is not this run's checkpoint"
            )
        return running["state"]

    def restore(self, algorithm: str, load_state: Callable[[dict[str, Any]], None]) -> bool:
        """Call ``load_state(state)`` with ``algorithm``'s saved state, if any; whatever it
        refuses becomes a ``CheckpointError`` naming the file. Returns whether it restored."""
        resumed, state = self.resumed, self.resume_state(algorithm)
        if state is None or resumed is None:  # a state comes from the resumed file
            return False
        try:
            load_state(state)
        except (KeyError, ValueError, TypeError, RuntimeError, AttributeError) as error:
            raise CheckpointError(
                f"checkpoint {resumed.path} does not fit this run: {error}"
            ) from None
        return True

    def finish(self, algorithm: str, metrics: dict[str, torch.Tensor]) -> None:
        """Record ``algorithm``'s final metrics (kept in later checkpoints)."""
        self.finished[algorithm] = {name: value.cpu() for name, value in metrics.items()}

    def save(self, algorithm: str | None, state: dict[str, Any] | None) -> Path:
        """Write a checkpoint now: the finished algorithms, and ``algorithm``'s ``state``."""
        started = time.perf_counter()
        content = {
            "config": self.config,
            "backend": self.backend,
            "every": None if self.every is None else str(self.every),
            "finished": self.finished,
            "running": None if algorithm is None else {"algorithm": algorithm, "state": state},
            "episodes_completed": self.episodes_completed,
            "experiments_finished": self.experiments_finished,
            "elapsed_s": self.elapsed_s,
            "saved_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        path = save(self.out, content)
        self.saved(started)
        return path


# --------------------------------------------------------------------------------------------
# The config of a resumed run (paper and compare)

#: Config fields a resumed run may change: they do not change the numbers.
RESUMABLE_CHANGES = ("out", "threads")


def resumed_config(
    saved: dict[str, Any],
    given: dict[str, Any],
    directory: str | os.PathLike,
    from_dict: Callable[[dict[str, Any]], Any],
    to_dict: Callable[[Any], dict[str, Any]],
) -> Any:
    """The config to resume the run of ``directory`` with: the checkpoint's ``saved`` config
    dict, with the ``given`` options (field -> value) that may change (``RESUMABLE_CHANGES``);
    ``from_dict`` / ``to_dict`` convert the command's config.

    Any other given option must equal the saved value (a ValueError names each that differs);
    ``out`` must be ``directory`` (the saved spelling is kept when it names the same directory,
    so the results repeat it). A saved config this program cannot use is a CheckpointError.
    """
    out = saved.get("out", "")
    if not out or Path(out).resolve() != Path(directory).resolve():
        out = str(directory)
    if "out" in given and Path(given["out"]).resolve() != Path(directory).resolve():
        raise ValueError(
            f"out='{given['out']}' differs from the resumed directory '{directory}': a resumed "
            f"run writes where its checkpoint is (leave --out out)"
        )
    try:
        checkpointed = from_dict({**saved, "out": out})
    except (ValueError, TypeError) as error:
        raise CheckpointError(
            f"resume='{directory}': the checkpoint's config is unusable here ({error})"
        ) from None
    merged = from_dict({**to_dict(checkpointed), **given, "out": out})
    check_same_config(saved, to_dict(merged), f"resume='{directory}'")
    return merged


def check_same_config(saved: dict[str, Any], config: dict[str, Any], what: str) -> None:
    """Refuse (ValueError naming each option) a ``config`` dict that differs from the ``saved``
    one in a field outside ``RESUMABLE_CHANGES``."""
    differing = [
        f"{name}={_show(value)} given, {_show(saved.get(name))} in the checkpoint"
        for name, value in config.items()
        if name not in RESUMABLE_CHANGES and saved.get(name) != value
    ]
    if differing:
        raise ValueError(
            f"{what} has a checkpoint of a different config: {'; '.join(differing)} (leave "
            f"these options out to resume it, or start a new run with another --out)"
        )


def _show(value: Any) -> str:
    return ",".join(map(str, value)) if isinstance(value, list | tuple) else repr(value)
