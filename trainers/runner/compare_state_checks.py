"""The checks of ``factorq compare``'s running state on resume: a method's saved state (online
methods: the collector, the world state, the recorder; DQN: its generator, loss, updates, the
Collector's carrier, policy, networks, optimiser and replay buffer) against a fresh state of the
method and its config's limits, before any of it is used (``factorq_trainers.runner.
compare_checkpoint`` holds the file format and the checks of its other fields).
"""

from __future__ import annotations

import math
import typing
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
import torch

from factorq_trainers.runner import checkpoint

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


def check_trace(
    trace: Any, world: str, index: int, experiments: Any, refuse: Callable[[str], Any]
) -> dict[str, Any]:
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
        if not checkpoint.is_int(value) or not 0 <= value <= experiments.steps:
            refuse(f"{where}: {name} must be an int in [0, {experiments.steps}]")
        out[name] = value
    return out


class Limits(NamedTuple):
    """What a method's saved state is checked against (``resume_checks.check_state`` reads a
    config by these fields): one run of ``episodes`` episodes per experiment."""

    runs: int
    episodes: int
    max_steps: int
    size: int
    obstacles: int
    world: Any
    steps: int
    #: Local rewards from tables lie in [-1, 0] (eq. 5 averages -1s and 0s); a network's may not.
    bounded_local_values: bool = True


def limits(experiments: Any, runs: int = 1, neural: bool = False) -> Limits:
    episodes = experiments.steps // (2 * (experiments.size - 1)) + 1
    return Limits(runs, episodes, experiments.max_steps, experiments.size, experiments.obstacles,
                  experiments.world, experiments.steps, not neural)  # fmt: skip


def _keys(state: Any, expected: tuple[str, ...] | set[str], where: str) -> None:
    if not isinstance(state, dict) or set(state) != set(expected):
        raise ValueError(f"{where} must hold exactly {', '.join(sorted(expected))}")


def _int(value: Any, low: int, high: int, where: str) -> int:
    if not checkpoint.is_int(value) or not low <= value <= high:
        raise ValueError(f"{where}={value!r} must be an int in [{low}, {high}]")
    return value


def check_step(state: dict[str, Any], steps: int, multiple: int = 1) -> int:
    """The env steps done, ``[1, steps - 1]`` (a multiple of ``multiple``)."""
    step = _int(state.get("step"), 1, steps - 1, "state['step']")
    if step % multiple:
        raise ValueError(f"state['step']={step} must be a multiple of {multiple}")
    return step


def check_like(saved: Any, fresh: Any, limit: Limits, periods: torch.Tensor, where: str) -> None:
    """``saved`` shaped like ``fresh`` (entries, shapes, dtypes, stream keys) with values in
    range (``resume_checks.check_state``)."""
    from factorq_trainers.runner import resume_checks

    resume_checks.check_state(saved, fresh, limit, periods, where)
    _check_constants(saved, fresh, where)


#: Entries of a module's state that a run never changes: the body's dependency, a network's
#: parent index, the discount, epsilon's schedule (DQN).
CONSTANTS = ("dependency", "parent_index", "gamma", "eps_init", "eps_end")


def _check_constants(saved: Any, fresh: Any, where: str) -> None:
    """Every ``CONSTANTS`` entry of ``saved`` equal to ``fresh``'s (same structure: checked)."""
    if isinstance(fresh, dict):
        for key, value in fresh.items():
            name = str(key).rsplit(".", 1)[-1]
            at = f"{where}[{key!r}]"
            if isinstance(value, torch.Tensor) and name in CONSTANTS:
                if not torch.equal(saved[key], value):
                    raise ValueError(f"{at} differs from this run's")
            else:
                _check_constants(saved[key], value, at)
    elif isinstance(fresh, list):
        for index, (item, reference) in enumerate(zip(saved, fresh, strict=True)):
            _check_constants(item, reference, f"{where}[{index}]")


def check_optimizer(saved: Any, optimizer: torch.optim.Optimizer, steps: int, where: str) -> None:
    """A saved ``state_dict`` of ``optimizer`` (SGD or Adam): the same param groups (learning
    rates, betas, ...) as this run's, and per parameter index at most Adam's ``step`` (a
    scalar in ``[0, steps]``) and moments shaped like the parameter, finite, the second >= 0."""
    fresh = optimizer.state_dict()
    _keys(saved, {"state", "param_groups"}, where)
    groups = saved["param_groups"]
    if not isinstance(groups, list) or len(groups) != len(fresh["param_groups"]):
        raise ValueError(f"{where}['param_groups'] must be a list of {len(fresh['param_groups'])}")
    for index, (group, reference) in enumerate(zip(groups, fresh["param_groups"], strict=True)):
        if not isinstance(group, dict) or group.keys() != reference.keys():
            raise ValueError(f"{where}['param_groups'][{index}] does not fit this optimiser")
        for key, value in reference.items():
            if type(group[key]) is not type(value) or group[key] != value:
                raise ValueError(
                    f"{where}['param_groups'][{index}][{key!r}]={group[key]!r} differs from this "
                    f"run's {value!r}"
                )
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    allowed = (
        {"step", "exp_avg", "exp_avg_sq"}
        if isinstance(optimizer, torch.optim.Adam)
        else {"momentum_buffer"}
    )
    state = saved["state"]
    if not isinstance(state, dict):
        raise ValueError(f"{where}['state'] must be a table")
    # Every parameter gets a gradient at every update: a state for all of them, or none yet.
    if state and set(state) != set(range(len(parameters))):
        raise ValueError(
            f"{where}['state'] must hold every parameter's state (0 to {len(parameters) - 1}) "
            f"or none"
        )
    if isinstance(optimizer, torch.optim.Adam):
        entries = [entry for entry in state.values() if isinstance(entry, dict)]
        if any(set(entry) != allowed for entry in entries):
            raise ValueError(
                f"{where}['state'] entries must hold exactly {', '.join(sorted(allowed))}"
            )
        counts = {float(e["step"]) for e in entries if isinstance(e["step"], torch.Tensor)}
        if len(counts) > 1:
            raise ValueError(f"{where}['state'] has parameters at different step counts")
    for index, entry in state.items():
        if not checkpoint.is_int(index) or not 0 <= index < len(parameters):
            raise ValueError(f"{where}['state'] has a key {index!r} that is no parameter's index")
        at = f"{where}['state'][{index}]"
        if not isinstance(entry, dict) or not set(entry) <= allowed:
            raise ValueError(f"{at} must hold at most {', '.join(sorted(allowed))}")
        parameter = parameters[index]
        for name, value in entry.items():
            if name == "momentum_buffer" and value is None:
                continue
            if not isinstance(value, torch.Tensor):
                raise ValueError(f"{at}[{name!r}] must be a tensor")
            shape, dtype = (
                ((), torch.float32) if name == "step" else (parameter.shape, parameter.dtype)
            )
            if tuple(value.shape) != tuple(shape) or value.dtype != dtype:
                raise ValueError(
                    f"{at}[{name!r}] has shape {tuple(value.shape)} and dtype {value.dtype}, "
                    f"expected {tuple(shape)} and {dtype}"
                )
            if not bool(torch.isfinite(value).all()):
                raise ValueError(f"{at}[{name!r}] holds NaN or infinite values")
            if name == "step" and not 0 <= float(value) <= steps:
                raise ValueError(f"{at}['step'] must be in [0, {steps}]")
            if name == "exp_avg_sq" and bool((value < 0).any()):
                raise ValueError(f"{at}['exp_avg_sq'] holds negative values")


_SUMS = ("steps", "collisions", "greedy", "task", "loss_sum", "loss_count")


def check_recorder(
    saved: Any, experiments: Any, step: int, where: str = "state['recorder']"
) -> dict[str, Any]:
    """An ``EpisodeRecorder.state_dict()`` after ``step`` env steps of every experiment: its
    traces as a finished method's (``check_trace``), the running sums float64 ``[E]``, whole,
    in range, and the episodes' steps adding up to ``step``. Returns the state with the traces'
    arrays checked."""
    _keys(saved, {"traces", "sums"}, where)
    labels = experiments.labels
    count = len(labels)

    def refuse(what: str) -> typing.NoReturn:
        raise ValueError(f"{where}: {what}")

    traces = saved["traces"]
    if not isinstance(traces, list) or len(traces) != count:
        refuse(f"traces must be a list of {count}")
    converted = [
        check_trace(trace, world, index, experiments, refuse)
        for (world, index), trace in zip(labels, traces, strict=True)
    ]
    sums = saved["sums"]
    _keys(sums, set(_SUMS), f"{where}['sums']")
    for name in _SUMS:
        value = sums[name]
        if (
            not isinstance(value, torch.Tensor)
            or value.dtype != torch.float64
            or tuple(value.shape) != (count,)
        ):
            refuse(f"sums[{name!r}] must be a float64 tensor of shape [{count}]")
        if not bool(torch.isfinite(value).all()):
            refuse(f"sums[{name!r}] holds NaN or infinite values")
        if name not in ("task", "loss_sum") and not bool((value == value.floor()).all()):
            refuse(f"sums[{name!r}] must hold whole numbers")
    high = experiments.max_steps - 1
    for name, low, top in (
        ("steps", 0.0, high),
        ("collisions", 0.0, high),
        ("greedy", 0.0, high),
        ("task", -float(experiments.max_steps), 0.0),
        ("loss_sum", 0.0, math.inf),
        ("loss_count", 0.0, high),
    ):
        value = sums[name]
        if bool((value < low).any()) or bool((value > top).any()):
            refuse(f"sums[{name!r}] holds values outside [{low:g}, {top:g}]")
    for row, trace in enumerate(converted):
        if trace["total_env_steps"] != step:
            refuse(f"the trace of {labels[row][0]}/seed_{labels[row][1]} has "
                   f"total_env_steps={trace['total_env_steps']}, not {step}")  # fmt: skip
        if int(trace["steps"].sum()) + int(sums["steps"][row]) != step:
            refuse(f"the episodes of {labels[row][0]}/seed_{labels[row][1]} do not add up to "
                   f"{step} steps")  # fmt: skip
    traces_out = [
        {key: torch.from_numpy(value) if isinstance(value, np.ndarray) else value
         for key, value in trace.items()}
        for trace in converted
    ]  # fmt: skip
    return {"traces": traces_out, "sums": {name: sums[name].clone() for name in _SUMS}}


def check_online_state(
    saved: Any, fresh: dict[str, Any], optimizer: Any, experiments: Any, neural: bool = False
) -> dict[str, Any]:
    """A running online method's state (tabular Factor-Q, Q-learning, Factor-DQN) against
    ``fresh`` (the same method's state before its first step): the step count, the collector's
    state (tables or networks, stream counters and keys, counters, metrics, observation) and the
    optimiser's, the world state and the records. Returns it with the records checked."""
    _keys(saved, set(fresh), "state")
    step = check_step(saved, experiments.steps)
    limit = limits(experiments, neural=neural)
    periods = torch.tensor(experiments.periods)
    collector = saved["collector"]
    if not isinstance(collector, dict) or "optimizer" not in collector:
        raise ValueError("state['collector'] must hold the optimizer's state")
    rest = {key: value for key, value in collector.items() if key != "optimizer"}
    reference = {key: value for key, value in fresh["collector"].items() if key != "optimizer"}
    check_like(rest, reference, limit, periods, "state['collector']")
    check_optimizer(collector["optimizer"], optimizer, step, "state['collector']['optimizer']")
    check_like(saved["world_state"], fresh["world_state"], limit, periods, "state['world_state']")
    return {**saved, "recorder": check_recorder(saved["recorder"], experiments, step)}


#: The entries of DQN's running state.
DQN_STATE = ("step", "rng", "loss", "updates", "world_state", "carrier", "policy", "loss_module",
             "optimizer", "buffer", "recorder")  # fmt: skip


def check_dqn_state(
    saved: Any,
    fresh: dict[str, Any],
    agent: Any,
    env: Any,
    config: Any,
    experiments: Any,
    stored: tuple[Any, ...],
) -> dict[str, Any]:
    """DQN's running state against ``fresh`` (its state before the first step) and the config
    (``DQNConfig``): a step count at a collector batch's end, a generator state torch accepts,
    the per-experiment losses (NaN before the first update), the target updater's counter, the
    world state, the collector's next observation, the networks (policy, loss module: target
    network included) and epsilon, Adam, the replay buffer (``check_buffer``; ``stored``: the
    entries it keeps) and the records.
    Returns it with the records checked."""
    _keys(saved, set(DQN_STATE), "state")
    step = check_step(saved, experiments.steps, config.train_every)
    count = experiments.num_experiments
    # the collector's trajectory ids count episodes of every experiment
    limit = limits(experiments, runs=count, neural=True)
    periods = torch.tensor(experiments.periods)
    rng = saved["rng"]
    reference = fresh["rng"]
    if (
        not isinstance(rng, torch.Tensor)
        or rng.dtype != reference.dtype
        or rng.shape != (reference.shape)
    ):
        raise ValueError(f"state['rng'] must be a {reference.dtype} tensor of {reference.numel()}")
    try:
        torch.Generator().set_state(rng)
    except RuntimeError as error:
        raise ValueError(f"state['rng'] is not a generator state torch accepts ({error})") from None
    loss = saved["loss"]
    if (
        not isinstance(loss, torch.Tensor)
        or loss.dtype != torch.float32
        or tuple(loss.shape) != (count,)
    ):
        raise ValueError(f"state['loss'] must be a float32 tensor of shape [{count}]")
    if bool(torch.isinf(loss).any()) or bool((loss < 0).any()):
        raise ValueError("state['loss'] must hold NaN (no update yet) or finite values >= 0")
    _int(saved["updates"], 0, config.target_update_interval, "state['updates']")
    check_like(saved["world_state"], fresh["world_state"], limit, periods, "state['world_state']")
    check_like(saved["carrier"], fresh["carrier"], limit, periods, "state['carrier']")
    check_like(saved["policy"], fresh["policy"], limit, periods, "state['policy']")
    check_like(saved["loss_module"], fresh["loss_module"], limit, periods, "state['loss_module']")
    for name, value in saved["policy"].items():
        if name.endswith(".eps"):
            if not config.eps_end <= float(value) <= config.eps_start:
                raise ValueError(
                    f"state['policy'][{name!r}]={float(value)} must be in "
                    f"[{config.eps_end}, {config.eps_start}]"
                )
    check_optimizer(saved["optimizer"], agent.optimizer, step, "state['optimizer']")
    check_buffer(saved["buffer"], fresh["buffer"], env, config, experiments, step, stored)
    return {**saved, "recorder": check_recorder(saved["recorder"], experiments, step)}


def check_buffer(
    saved: Any,
    fresh: dict[str, Any],
    env: Any,
    config: Any,
    experiments: Any,
    step: int,
    stored: tuple[Any, ...],
) -> None:
    """A ``ReplayBuffer.state_dict()`` after ``step`` env steps: one row per step written round
    robin into ``buffer_size`` rows (so its length, cursor and write count follow from ``step``),
    everything else as this run's fresh buffer, and the rows written shaped like the env's
    transitions (``[buffer_size, E, ...]``, their dtypes) with values the env can produce."""
    where = "state['buffer']"
    _keys(saved, set(fresh), where)
    for key, value in fresh.items():
        if (
            key != "_storage"
            and key != "_writer"
            and (type(saved[key]) is not type(value) or saved[key] != value)
        ):
            raise ValueError(f"{where}[{key!r}] differs from this run's")
    capacity = config.buffer_size
    length = min(step, capacity)
    writer = {"_cursor": step % capacity, "_write_count": step}
    if saved["_writer"] != writer or type(saved["_writer"]) is not dict:
        raise ValueError(f"{where}['_writer'] must be {writer} after {step} steps")
    storage = saved["_storage"]
    _keys(storage, {"_storage", "initialized", "_len"}, f"{where}['_storage']")
    if (
        storage["initialized"] is not True
        or storage["_len"] != length
        or not checkpoint.is_int(storage["_len"])
    ):
        raise ValueError(f"{where}['_storage'] must be initialised and hold {length} rows")
    rows = storage["_storage"]
    world = experiments.world
    reference = env.fake_tensordict().select(*stored, strict=False)
    bounds = {"cell": world.num_cells, "action": world.num_actuators,
              "heading": world.num_headings}  # fmt: skip
    # TensorDict's state_dict names a nested entry "next.cell".
    expected = {
        key if isinstance(key, str) else ".".join(key): reference.get(key)
        for key in reference.keys(include_nested=True, leaves_only=True)
    }
    if not isinstance(rows, dict):
        raise ValueError(f"{where}['_storage']['_storage'] must be a table of tensors")
    found = dict(rows)
    if set(found) != set(expected):
        raise ValueError(f"{where} must store exactly {', '.join(sorted(expected))}")
    for key, value in found.items():
        like = expected[key]
        at = f"{where} entry {key}"
        shape = (capacity, *like.shape)
        if (
            not isinstance(value, torch.Tensor)
            or tuple(value.shape) != shape
            or (value.dtype != like.dtype)
        ):
            raise ValueError(f"{at} must be a {like.dtype} tensor of shape {list(shape)}")
        written = value[:length]
        leaf = key.rsplit(".", 1)[-1]
        if written.is_floating_point():
            if not bool(torch.isfinite(written).all()):
                raise ValueError(f"{at} holds NaN or infinite values")
            low, high = -1.0 - world.num_actuators, 1.0  # step + goal + collisions
        elif written.dtype == torch.bool:
            continue
        else:
            low, high = 0, bounds.get(leaf, experiments.max_steps + 1) - 1
        if written.numel() and (bool((written < low).any()) or bool((written > high).any())):
            raise ValueError(f"{at} holds values outside [{low}, {high}]")
