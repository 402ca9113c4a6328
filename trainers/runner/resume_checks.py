"""Untrusted checkpoint state of ``factorq paper``, checked before anything reaches the kernel or
the env: a checkpoint's digest proves the file is intact, not who wrote it, so every
field is compared with the run's config and with a fresh batch of the run (entries, shapes, dtypes,
ranges, finiteness, the world's invariants), and refused in one line naming the field.

``paper`` calls ``check_checkpoint`` when a run resumes and ``check_state`` in its drivers; this
module does not import ``paper`` (the config is read by its fields).
"""

from __future__ import annotations

import typing
from collections.abc import Callable, Iterator
from typing import Any

import torch

from factorq_envs.grid_world import NUM_ACTIONS
from factorq_trainers.runner import checkpoint

#: The experiment drivers a checkpoint may come from (``paper.BACKENDS`` less ``auto``).
DRIVERS = ("fast", "modular")


def check_checkpoint(resume: checkpoint.Checkpoint, config: Any) -> None:
    """Refuse (``CheckpointError``, one line) a checkpoint whose content does not fit ``config``:
    the progress counters, the finished algorithms' metrics (names, shapes, dtypes, ranges,
    finiteness), which algorithm was running, and every float in its saved state finite. The
    backend's own loader then checks the state's fields (``ExperimentBatch.load_state_dict``,
    ``OnlineCollector.load_state_dict``) before anything reaches the kernel."""

    def refuse(what: str) -> typing.NoReturn:
        raise checkpoint.CheckpointError(f"checkpoint {resume.path} is not usable: {what}")

    count = len(config.worlds) * config.seeds
    experiments_total = count * len(config.algorithms)
    episodes_total = experiments_total * config.runs * config.episodes
    if resume.backend not in DRIVERS:
        refuse(f"backend={resume.backend!r} is not one of {', '.join(DRIVERS)}")
    if not 0 <= resume.episodes_completed <= episodes_total:
        refuse(f"episodes_completed={resume.episodes_completed} is not in [0, {episodes_total}]")
    if not 0 <= resume.experiments_finished <= experiments_total:
        refuse(
            f"experiments_finished={resume.experiments_finished} is not in [0, {experiments_total}]"
        )
    finished = list(resume.finished)
    if finished != list(config.algorithms[: len(finished)]):
        refuse(f"finished={finished} are not the first algorithms of {list(config.algorithms)}")
    shape = (count, config.runs, config.episodes)
    for algorithm, metrics in resume.finished.items():
        if not isinstance(metrics, dict) or sorted(metrics) != sorted(METRIC_DTYPES):
            refuse(f"finished[{algorithm!r}] must hold the metrics {', '.join(METRIC_DTYPES)}")
        for name, dtype in METRIC_DTYPES.items():
            check_metric(f"finished[{algorithm!r}][{name!r}]", metrics[name], shape, dtype,
                         config.max_steps, refuse)  # fmt: skip
    running = resume.running
    if running is not None:
        if set(running) != {"algorithm", "state"} or not isinstance(running["state"], dict):
            refuse("running must hold an algorithm and its state")
        expected = (
            config.algorithms[len(finished)] if len(finished) < len(config.algorithms) else None
        )
        if running["algorithm"] != expected:
            refuse(f"running algorithm {running['algorithm']!r} is not the next one, {expected!r}")
        for where, tensor in _tensors(running["state"], "running state"):
            if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
                refuse(f"{where} holds NaN or infinite values")


def check_state(
    saved: Any, fresh: Any, config: Any, periods: torch.Tensor, where: str = "state"
) -> None:
    """Refuse (ValueError naming the entry) a saved driver state that is not shaped like
    ``fresh`` (the state of a new batch of this run: same keys, list lengths, tensor shapes and
    dtypes, equal constants, equal stream keys) or holds a value no run of ``config`` can reach:
    a cell off the grid, a counter below 0 or above what ``runs x episodes x max_steps`` steps
    can count, a run or an episode past the end, a local reward outside ``[-1, 0]``, NaN or
    infinite numbers, obstacles that are not ``config.obstacles`` cells off the start and goal
    and the agent (the static layout in a static world)."""
    if where.endswith("['observation']") and fresh is None:
        count = periods.numel()
        _check_observation(saved, count, config, where)
        return
    if isinstance(fresh, dict):
        if fresh.keys() != (saved.keys() if isinstance(saved, dict) else None):
            raise ValueError(f"{where} must hold exactly the entries {sorted(map(str, fresh))}")
        for key in fresh:
            check_state(saved[key], fresh[key], config, periods, f"{where}[{key!r}]")
        _check_world(saved, config, periods, where)
    elif isinstance(fresh, list):
        if not isinstance(saved, list) or len(saved) != len(fresh):
            raise ValueError(f"{where} must be a list of {len(fresh)} entries")
        for index, (item, reference) in enumerate(zip(saved, fresh, strict=True)):
            check_state(item, reference, config, periods, f"{where}[{index}]")
    elif isinstance(fresh, torch.Tensor):
        if not isinstance(saved, torch.Tensor):
            raise ValueError(f"{where} must be a tensor, got {type(saved).__name__}")
        if saved.shape != fresh.shape or saved.dtype != fresh.dtype:
            raise ValueError(
                f"{where} has shape {tuple(saved.shape)} and dtype {saved.dtype}, expected "
                f"{tuple(fresh.shape)} and {fresh.dtype}"
            )
        _check_values(saved, fresh, config, where)
    elif type(saved) is not type(fresh) or saved != fresh:
        raise ValueError(f"{where}={saved!r} differs from this run's {fresh!r}")


#: dtype of the observation entries a saved collector state must have (others may be there too:
#: the env's keys depend on the body), and those it must hold.
OBSERVATION_DTYPES = {
    **dict.fromkeys(("cell", "action", "run", "episode", "heading"), torch.int64),
    **dict.fromkeys(
        ("proximity", "sensors", "bump", "mask", "exploratory", "done", "terminated", "truncated"),
        torch.bool,
    ),
    **dict.fromkeys(("collision", "action_value", "local_value", "combined_value"), torch.float32),
}
OBSERVATION_REQUIRED = ("cell", "bump", "collector", "action", "done", "terminated", "truncated")


def _check_observation(saved: Any, count: int, config: Any, where: str) -> None:
    """The observation a collector's next step acts on: None (saved before its first step) or
    a table of ``[S, ...]`` tensors with the entries and dtypes it needs, values in range."""
    if saved is None:
        return
    if not isinstance(saved, dict) or not set(OBSERVATION_REQUIRED) <= set(saved):
        raise ValueError(f"{where} must hold {', '.join(OBSERVATION_REQUIRED)}")
    if not isinstance(saved["collector"], dict) or set(saved["collector"]) != {
        "mask",
        "run",
        "episode",
    }:
        raise ValueError(f"{where}['collector'] must hold exactly mask, run and episode")
    for name, value in _tensors(saved, where):
        leaf = name.rsplit("[", 1)[-1].strip("]'")
        if value.dim() == 0 or value.shape[0] != count:
            raise ValueError(f"{name} must have {count} rows")
        if leaf in OBSERVATION_DTYPES and value.dtype != OBSERVATION_DTYPES[leaf]:
            raise ValueError(f"{name} has dtype {value.dtype}, expected {OBSERVATION_DTYPES[leaf]}")
        _check_values(value, None, config, name)
    for name, value in _leaves(saved, where):
        if not isinstance(value, torch.Tensor):
            raise ValueError(f"{name} must be a tensor, got {type(value).__name__}")


def _leaves(tree: Any, where: str) -> Iterator[tuple[str, Any]]:
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _leaves(value, f"{where}[{key!r}]")
    else:
        yield where, tree


def _check_values(value: torch.Tensor, fresh: torch.Tensor | None, config: Any, where: str) -> None:
    name = where.rsplit("[", 1)[-1].strip("]'").rsplit(".", 1)[-1].rsplit("/", 1)[-1]
    if value.numel() == 0 or value.dtype == torch.bool:
        return
    if "keys" in name or name == "periods":  # the batch's identity: the run's own streams
        if fresh is None or not torch.equal(value, fresh):
            raise ValueError(f"{where} belongs to a different batch")
        return
    if value.is_floating_point():
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{where} holds NaN or infinite values")
        low, high = {"rho": (-1.0, 0.0), "local_value": (-1.0, 0.0)}.get(name, (None, None))
        if not getattr(config, "bounded_local_values", True):  # a network's, not a table's
            low, high = None, None
        if "return" in name:
            low, high = -float(config.max_steps), 0.0
    else:
        steps = config.runs * config.episodes * (config.max_steps + 1) + 1
        cells = config.size**2
        low, high = (
            0,
            {
                "cell": cells - 1,
                "action": NUM_ACTIONS - 1,
                "run": config.runs,
                "run_index": config.runs,
                "episode": config.episodes - 1,
                "episode_index": config.episodes - 1,
                "episode_step": config.max_steps - 1,
            }.get(
                name, config.max_steps if name in METRIC_NAMES or "collisions" in name else steps
            ),
        )
    if (
        low is not None
        and high is not None
        and (bool((value < low).any()) or bool((value > high).any()))
    ):
        raise ValueError(f"{where} holds values outside [{low}, {high}]")


#: Names of per-episode counts (metrics and the running episode's sums): at most max_steps.
METRIC_NAMES = ("steps", "collisions", "greedy_collisions")


def _check_world(state: dict[str, Any], config: Any, periods: torch.Tensor, where: str) -> None:
    """The obstacles and the agent of a saved world state (``obstacles`` ``[S, N]`` bool beside
    ``cell`` ``[S]``): ``config.obstacles`` cells per world, never the start, the goal or the
    agent's cell, the static layout where the world is static."""
    obstacles, cell = state.get("obstacles"), state.get("cell")
    if not isinstance(obstacles, torch.Tensor) or not isinstance(cell, torch.Tensor):
        return
    if obstacles.dtype != torch.bool or obstacles.dim() != 2 or cell.shape != obstacles.shape[:1]:
        return  # the shape checks name it
    if bool((obstacles.sum(dim=1) != config.obstacles).any()):
        raise ValueError(f"{where}['obstacles'] must hold obstacles={config.obstacles} per world")
    if bool(obstacles[:, 0].any()) or bool(obstacles[:, -1].any()):
        raise ValueError(f"{where}['obstacles'] covers the start or the goal")
    inside = (cell >= 0) & (cell < obstacles.shape[1])
    if bool(inside.all()) and bool(obstacles.gather(1, cell.unsqueeze(1)).any()):
        raise ValueError(f"{where}['cell'] is on an obstacle")
    static = periods == 0
    if bool(static.any()) and config.obstacles:
        from factorq_envs.grid_world import static_layout

        if not bool((obstacles[static] == static_layout(config.world)).all()):
            raise ValueError(f"{where}['obstacles'] of a static world is not its layout")


#: dtype of every per-episode metric ``[S, runs, episodes]``.
METRIC_DTYPES = {
    "steps": torch.int64,
    "collisions": torch.int64,
    "greedy_collisions": torch.int64,
    "task_return": torch.float32,
}


def check_metric(
    where: str,
    value: Any,
    shape: tuple[int, ...],
    dtype: torch.dtype,
    max_steps: int,
    refuse: Callable[[str], typing.NoReturn],
) -> None:
    """Refuse a per-episode metric that is not a ``shape`` tensor of ``dtype`` with values an
    episode of at most ``max_steps`` steps can have (counts in ``[0, max_steps]``, returns
    finite and in ``[-max_steps, 0]``)."""
    if not isinstance(value, torch.Tensor):
        refuse(f"{where} is a {type(value).__name__}, not a tensor")
    if tuple(value.shape) != shape or value.dtype != dtype:
        refuse(
            f"{where} has shape {tuple(value.shape)} and dtype {value.dtype}, expected {shape} "
            f"and {dtype}"
        )
    if value.numel() == 0:
        return
    if dtype.is_floating_point:
        if not bool(torch.isfinite(value).all()):
            refuse(f"{where} holds NaN or infinite values")
        low, high = -float(max_steps), 0.0
    else:
        low, high = 0, max_steps
    if bool((value < low).any()) or bool((value > high).any()):
        refuse(f"{where} holds values outside [{low:g}, {high:g}]")


def _tensors(tree: Any, where: str) -> Iterator[tuple[str, torch.Tensor]]:
    """``(path, tensor)`` for every tensor in nested dicts and lists."""
    if isinstance(tree, torch.Tensor):
        yield where, tree
    elif isinstance(tree, dict):
        for key, value in tree.items():
            yield from _tensors(value, f"{where}[{key!r}]")
    elif isinstance(tree, list | tuple):
        for index, value in enumerate(tree):
            yield from _tensors(value, f"{where}[{index}]")
