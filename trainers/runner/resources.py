"""What a run will need, estimated from its config before any work, against what the machine has.

``paper_estimate(config)`` and ``compare_estimate(config)`` add up the big allocations a run
makes, from its config alone (no tensor is allocated): the tables ``[E, states, 4]`` float32,
the kernel's or the env's per-experiment state, the metrics ``[E, runs, episodes]``, the
per-episode curves of the results, DQN's replay buffer, networks (weights, gradients, Adam's
moments, the target copy) and minibatch activations, and the per-episode records of
``factorq compare``. It is an estimate: the constant overhead of Python, torch and torchrl
(already loaded when it is made) is left out, and small per-run tensors are rounded up.

``check(estimate)`` compares it with the memory available (``available_memory``: the least of
``MemAvailable`` in ``/proc/meminfo``, the cgroup's limit minus its usage, and
``FACTORQ_MEMORY_LIMIT`` in bytes when set) and raises a ``ResourceError`` naming the estimate,
its largest parts and the limit when the run would not fit; it returns a line to print for a run
that fits but is large (at least ``LARGE_BYTES`` or a quarter of what is available), with the
number of env steps it will take, the cheap part of a time estimate.

>>> from factorq_trainers.experiments.paper import PaperConfig
>>> estimate = paper_estimate(PaperConfig())
>>> 30 * 2**20 < estimate.bytes < 120 * 2**20  # the default run: some 56 MiB (measured 60)
True
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

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
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                limits.append((int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"))
    except (OSError, ValueError, IndexError):
        pass
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
    task's estimate is its command's, ``compare_estimate``, ``dependencies_estimate``, ...),
    and the env steps of every task, as a run's estimate counts its own."""
    largest = max(tasks, key=lambda estimate: estimate.bytes)
    at_once = min(max(workers, 1), len(tasks))
    suffix = f" x {at_once} at once" if at_once > 1 else ""
    parts = {name + suffix: value * at_once for name, value in largest.parts.items()}
    steps = sum(estimate.env_steps for estimate in tasks)
    return Estimate(parts, steps, exact_steps=all(estimate.exact_steps for estimate in tasks))


def compare_estimate(config: Any) -> Estimate:
    """Peak memory of ``factorq compare`` with ``config`` (a ``CompareConfig``): the largest
    method's tables, networks and replay buffer, and every method's per-episode records (kept
    until the summary, as each unit's result; counted as if every episode were as short as
    possible)."""
    experiments = config.experiments
    count = experiments.num_experiments
    world = experiments.world
    cells = experiments.size**2 * world.num_headings
    sensors, actions = world.num_sensors, world.num_actuators
    # An episode takes at least the Manhattan distance: at most this many fit the budget.
    episodes = experiments.steps // (2 * (experiments.size - 1)) + 1
    # Per episode: 7 records as Python floats in lists, their numpy copies, the collector's
    # metrics [E, 1, episodes] (4 x 8 bytes).
    records = count * episodes * (7 * 32 + 7 * 8 + 32)
    largest: dict[str, int] = {}
    for method in config.methods:
        parts: dict[str, int] = {}
        if method == "q-learning":
            parts["tables"] = count * (cells << sensors) * actions * 4
        elif method == "factor-q":
            parts["tables"] = count * (cells * actions * 4 + actions * (2 << sensors) * 12)
        elif method == "factor-dqn":
            settings = config.factor_dqn
            weights = _mlp_weights(cells, settings.hidden, actions)
            copies = 1 if settings.local_shared else actions
            weights += _mlp_weights(sensors, settings.local_hidden, 1) * copies
            # weights, gradients, Adam's two moments; activations of one step
            parts["networks"] = count * (4 * weights * 4 + 4 * (cells + sum(settings.hidden)) * 3)
        else:  # dqn
            settings = config.dqn
            weights = _mlp_weights(cells + sensors, settings.hidden, actions)
            width = cells + sensors + sum(settings.hidden) + actions
            parts["networks"] = count * 5 * weights * 4  # + gradients, Adam moments, target copy
            # A minibatch [B, E]: its one-hot features and activations, forward and backward,
            # for the network and the target network.
            parts["minibatch"] = settings.batch_size * count * width * 4 * 3
            # One row [E] of 38 bytes per stored transition, and the collector's batch of
            # train_every steps of every experiment (all of a step's entries, ~200 bytes each).
            parts["replay buffer"] = min(settings.buffer_size, experiments.steps) * count * 38
            parts["collector"] = settings.train_every * count * (200 + 4 * width)
        parts["env"] = count * (cells + EXPERIMENT_BYTES)
        if sum(parts.values()) > sum(largest.values()):
            largest = parts
    largest["episode records"] = records * len(config.methods)
    points = len(config.methods) * len(experiments.worlds) * 100 * 6 * 56  # the curves
    largest["curves"] = points
    return Estimate(largest, len(config.methods) * count * experiments.steps, exact_steps=True)


def _mlp_weights(inputs: int, hidden: tuple[int, ...], outputs: int) -> int:
    """Weights and biases of one MLP ``inputs -> hidden... -> outputs``."""
    widths = [inputs, *hidden, outputs]
    return sum(a * b + b for a, b in zip(widths, widths[1:], strict=False))


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


def info(estimate: Estimate) -> dict[str, Any]:
    """The estimate as JSON-ready numbers (for logs and tests)."""
    return {"bytes": estimate.bytes, "parts": dict(estimate.parts), "env_steps": estimate.env_steps}


#: What to make smaller (a command declares its own ``HINT``).
COMPARE_HINT = "use fewer --seeds or --steps, or a smaller --size"
