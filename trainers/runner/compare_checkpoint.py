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
            converted.append(_check_trace(trace, world, index, experiments, refuse))
        resume.finished[method] = {"traces": converted, "wall_s": wall}
    if resume.running is not None:
        pending = [method for method in config.methods if method not in resume.finished]
        if not pending or resume.running["method"] != pending[0]:
            refuse(
                f"running method {resume.running['method']!r} is not the next one to run, "
                f"{pending[0] if pending else None!r}"
            )


def _check_trace(
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
        if running is None:
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
    traces as a finished method's (``_check_trace``), the running sums float64 ``[E]``, whole,
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
        _check_trace(trace, world, index, experiments, refuse)
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
