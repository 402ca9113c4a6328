"""What a run will need, estimated from its config before any work, against what the machine has.

Each command's ``estimate(config)`` adds up the big allocations its run makes from the config
alone (no tensor is allocated; the constant overhead of Python and torch is left out, small
tensors rounded up); this module holds what they share: ``Estimate``, the byte sizes, and
``check``, which refuses a run that would not fit in ``available_memory`` (the least of
``MemAvailable``, the cgroup's limit minus its usage and ``FACTORQ_MEMORY_LIMIT``) with a
``ResourceError`` naming the estimate, its largest parts and the limit, and returns a line to
print for a large run that fits.

>>> from factorq_trainers.commands.paper import command as paper
>>> estimate = paper.estimate(paper.PaperConfig())
>>> 30 * 2**20 < estimate.bytes < 120 * 2**20  # the default run: some 59 MiB
True
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import NamedTuple

#: A run needing at least this much memory prints its estimate before it starts.
LARGE_BYTES = 2**30
#: Overrides (lowers) the memory limit, in bytes: for tests, and for users sharing a machine.
LIMIT_VARIABLE = "FACTORQ_MEMORY_LIMIT"
#: Bytes per episode of metrics: steps, collisions, greedy collisions (int64), task return (f32).
METRIC_BYTES = 8 + 8 + 8 + 4
#: Bytes per point of a per-episode curve in the results: a Python float in a list, and its
#: JSON text (mean, low and high, for each of the 3 curves).
CURVE_POINT_BYTES = 9 * (32 + 24)
#: Bytes per experiment of the kernel's and the env's small per-experiment state (keys, counters,
#: local tables, bump bits, per-episode sums), rounded up.
EXPERIMENT_BYTES = 512


class ResourceError(ValueError):
    """A run that would not fit in the memory available: the estimate and the limit, one line."""


class Estimate(NamedTuple):
    """Bytes a run needs at its peak, by part, and the env steps it will take at least."""

    parts: dict[str, int]
    env_steps: int
    exact_steps: bool

    @property
    def bytes(self) -> int:
        return sum(self.parts.values())


def human_bytes(count: float) -> str:
    """``1536`` -> ``'1.5 KiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(count) < 1024 or unit == "PiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    raise AssertionError("unreachable")


def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().strip()
    except OSError:
        return None
    return int(text) if text.isdigit() else None


def available_memory() -> tuple[int | None, str]:
    """``(bytes, where that figure comes from)``: the least of the limits found, or ``(None,
    reason)`` where none can be read (then nothing is refused)."""
    limits: list[tuple[int, str]] = []
    override = os.environ.get(LIMIT_VARIABLE)
    if override is not None:
        if not override.strip().isdigit():
            raise ResourceError(
                f"{LIMIT_VARIABLE}={override!r} must be a number of bytes (e.g. 8000000000)"
            )
        limits.append((int(override), LIMIT_VARIABLE))
    with contextlib.suppress(OSError, ValueError, IndexError):
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                limits.append((int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"))
    cgroup = Path("/sys/fs/cgroup")
    for limit_file, usage_file in (
        ("memory.max", "memory.current"),  # cgroup v2
        ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes"),  # cgroup v1
    ):
        limit, usage = _read_int(cgroup / limit_file), _read_int(cgroup / usage_file)
        if limit is not None and limit < 2**60:  # v1 writes a huge number for "no limit"
            limits.append((max(limit - (usage or 0), 0), f"the cgroup limit ({limit_file})"))
    if not limits:
        return None, "unknown (no /proc/meminfo or cgroup limit here)"
    return min(limits)


def tasks_estimate(tasks: list[Estimate], workers: int) -> Estimate:
    """Peak memory and env steps of a sweep whose configurations each run whole, as tasks
    (``compare``'s, a command of the runner's): ``workers`` of its largest task at once (each
    task's estimate is its command's ``estimate``),
    and the env steps of every task, as a run's estimate counts its own."""
    largest = max(tasks, key=lambda estimate: estimate.bytes)
    at_once = min(max(workers, 1), len(tasks))
    suffix = f" x {at_once} at once" if at_once > 1 else ""
    parts = {name + suffix: value * at_once for name, value in largest.parts.items()}
    steps = sum(estimate.env_steps for estimate in tasks)
    return Estimate(parts, steps, exact_steps=all(estimate.exact_steps for estimate in tasks))


def describe(estimate: Estimate) -> str:
    """``about 2.1 GiB of memory (tables 1.9 GiB, metrics 200.0 MiB)`` (the largest parts)."""
    parts = sorted(estimate.parts.items(), key=lambda item: -item[1])
    shown = ", ".join(f"{name} {human_bytes(value)}" for name, value in parts[:3] if value)
    return f"about {human_bytes(estimate.bytes)} of memory ({shown})"


def check(estimate: Estimate, what: str, hint: str) -> str | None:
    """Refuse a run that would not fit (``ResourceError``: estimate, limit and ``hint``, what to
    make smaller); for a large one that fits, return a line to print; else None."""
    available, source = available_memory()
    steps = f"{'' if estimate.exact_steps else 'at least '}{estimate.env_steps:.3g} env steps"
    if available is not None and estimate.bytes > available:
        raise ResourceError(
            f"this {what} needs {describe(estimate)} but {human_bytes(available)} is available "
            f"({source}): {hint}"
        )
    if estimate.bytes >= LARGE_BYTES or (available is not None and estimate.bytes * 4 > available):
        of = "" if available is None else f" of the {human_bytes(available)} available"
        return f"this {what} needs {describe(estimate)}{of}, and {steps}"
    return None
